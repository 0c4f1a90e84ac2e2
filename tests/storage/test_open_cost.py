"""Opening a map is O(1): it reads a few meta records and touches no shard, edge or index data.

Not a timing test (``tools/bench_store.py`` measures open time at 10k vs 1M vertices): here every
way of reading bulk data is made to fail during open, and the LMDB look-ups open makes are
counted and must not depend on the size of the map.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import faiss
import pytest

from sprint_map.storage.components import ComponentStore
from sprint_map.storage.index.map_index import IndexStore
from sprint_map.storage.lmdb_env import LmdbEnv
from sprint_map.storage.shards import ShardSet
from sprint_map.storage.store import MapStore


class ForbiddenDuringOpen(AssertionError):
    pass


class GuardedTxn:
    """A read transaction that counts point look-ups and refuses cursors (scans)."""

    def __init__(self, txn: Any, gets: list[bytes]) -> None:
        self._txn = txn
        self._gets = gets

    def get(self, key: bytes, *args: Any, **kwargs: Any) -> Any:
        self._gets.append(bytes(key))
        return self._txn.get(key, *args, **kwargs)

    def cursor(self, *args: Any, **kwargs: Any) -> Any:
        raise ForbiddenDuringOpen("cursor (scan) opened while opening the map")

    def __getattr__(self, name: str) -> Any:
        return getattr(self._txn, name)


def _forbid(*args: Any, **kwargs: Any) -> Any:
    raise ForbiddenDuringOpen("bulk data read while opening the map")


@pytest.fixture
def arm_guard(monkeypatch) -> Callable[[], list[bytes]]:
    """Call it (after building the maps) to make bulk reads fail; it returns the list that
    records every LMDB look-up made from then on."""

    def arm() -> list[bytes]:
        gets: list[bytes] = []
        original_read = LmdbEnv.read

        @contextmanager
        def read(self: LmdbEnv) -> Iterator[GuardedTxn]:
            with original_read(self) as txn:
                yield GuardedTxn(txn, gets)

        monkeypatch.setattr(LmdbEnv, "read", read)
        for cls, names in (
            (ShardSet, ("rows", "take", "_map")),
            (IndexStore, ("load", "catch_up")),
            (ComponentStore, ("members", "components", "find")),
            (MapStore, ("sequences", "edges", "edges_from", "components", "disk_bytes")),
        ):
            for name in names:
                monkeypatch.setattr(cls, name, _forbid)
        monkeypatch.setattr(faiss, "read_index", _forbid)
        return gets

    return arm


@pytest.mark.parametrize("readonly", [True, False], ids=["reader", "writer"])
def test_open_reads_no_bulk_data_and_a_constant_number_of_records(make_map, arm_guard, readonly):
    small = make_map((3,), shard_rows=4)
    large = make_map([5, 9, 1, 30, 7] * 12, shard_rows=4, edges=2)  # 60 seqs, 78 shards
    gets = arm_guard()
    counts = []
    for built in (small, large):
        gets.clear()
        store = MapStore.open(built.path, readonly=readonly)
        counts.append(sorted(gets))
        store.env.close()  # not close(): a writer's close would persist (load) the index
        if store.writer_lock is not None:
            store.writer_lock.release()
    assert counts[0] == counts[1]
    assert len(counts[0]) <= 8


def test_guard_catches_a_bulk_read(make_map, arm_guard):
    """The guard itself works: a call that does read bulk data fails under it."""
    built = make_map((3,))
    arm_guard()
    store = MapStore.open(built.path, readonly=True)
    try:
        with pytest.raises(ForbiddenDuringOpen):
            store.descriptors(0)
        with pytest.raises(ForbiddenDuringOpen):
            store.edges()
    finally:
        store.env.close()
