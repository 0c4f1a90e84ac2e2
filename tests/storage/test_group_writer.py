"""GroupWriter (sprint_map/storage/group_writer.py): several sequences, one fsync of their rows,
one LMDB transaction; each sequence whole or absent.

Kills at the group's crash points run in ``tests/merge/test_drives.py`` (a real ``ingest --no-merge``)
and in the random-kill loop of ``tests/helpers/crash_worker.py`` (its writers commit groups too); power
loss and I/O errors at every file call of a group in ``tests/storage/test_faults.py``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sprint_map.errors import (
    DuplicateNameError,
    EmptySequenceError,
    InputError,
    SprintMapError,
)
from sprint_map.storage.check import check_map
from sprint_map.storage.records import EdgeSpec
from sprint_map.storage.store import SHARDS_DIR, MapStore
from sprint_map.testing.faults import CallRecorder, installed
from tests.helpers import crash_worker

SEED, DIM = 3, 16
CONFIG = {"dim": DIM, "shard_rows": 64}


def state(path: Path) -> dict[str, Any]:
    with MapStore.open(path, readonly=True) as store:
        report = check_map(store)
        assert report.ok, report.violations
        # no row is left past the committed end of the shards
        assert not [n for n in report.notes if "uncommitted" in n], report.notes
        out = crash_worker.logical_state(store)
    out["edges"] = {e[:-1] for e in out["edges"]}  # the edge's commit time aside
    return out


def add_group(store: MapStore, indices: range) -> list[Any]:
    """Sequences ``indices`` of the worker stream in one group (streamed every third, as
    ``add_planned`` does; their edges reach earlier sequences, of the group too)."""
    with store.begin_group() as group:
        for i in indices:
            plan = crash_worker.planned_sequence(SEED, i, DIM)
            rows = (plan.descriptors if i % 3 != 1 else
                    iter(np.array_split(plan.descriptors, 3)))
            group.add(rows, plan.name, "", plan.positions, plan.edges, plan.thumbnails)
        return group.commit()


def test_a_group_equals_its_sequences_added_one_by_one(tmp_path):
    one, grouped = tmp_path / "one", tmp_path / "grouped"
    for path in (one, grouped):
        crash_worker.create_map(path, **CONFIG)
    with MapStore.open(one) as store:
        for i in range(9):
            crash_worker.add_planned(store, SEED, i)
    with MapStore.open(grouped) as store:
        crash_worker.add_planned(store, SEED, 0)
        txn = store.env.env.info()["last_txnid"]
        recorder = CallRecorder()
        with installed(recorder):
            results = add_group(store, range(1, 9))
        assert store.env.env.info()["last_txnid"] == txn + 1  # one transaction
        assert store.writing is None
    assert [r.sequence.seq_id for r in results] == list(range(1, 9))
    assert any(r.edges_added for r in results)
    shards = {p for op, p in recorder.calls if op == "write"}
    assert len(shards) > 1  # the group's rows span shard files ...
    fsyncs = [p for op, p in recorder.calls if op == "fsync"]
    assert sorted(fsyncs) == sorted(shards)  # ... each fsynced once, at the commit
    assert state(grouped) == state(one)
    crash_worker.assert_search_finds_everything(grouped)


def test_abort_leaves_nothing_and_the_writer_goes_on(tmp_path):
    path = tmp_path / "m"
    crash_worker.create_map(path, **CONFIG)
    with MapStore.open(path) as store:
        crash_worker.add_planned(store, SEED, 0)
        before = state_files(path)
        with store.begin_group() as group:
            for i in (1, 2, 3):
                plan = crash_worker.planned_sequence(SEED, i, DIM)
                group.add(plan.descriptors, plan.name)
            assert group.frames == sum(r.length for r in group.staged) > 0
            # nothing committed, and nothing else may be written meanwhile
            assert store.stats()["sequences"] == 1
            with pytest.raises(SprintMapError, match="already being written"):
                store.add_sequence(np.ones((2, DIM)))
            with pytest.raises(SprintMapError, match="being written"):
                store.remove_sequences([0])
        assert state_files(path) == before  # the group's rows truncated away
        crash_worker.add_planned(store, SEED, 1)
    assert list(state(path)["sequences"]) == [0, 1]


def state_files(path: Path) -> dict[str, int]:
    return {p.name: p.stat().st_size for p in (path / SHARDS_DIR).iterdir()}


def test_a_failing_sequence_is_dropped_and_the_group_goes_on(tmp_path, rng):
    path = tmp_path / "m"
    crash_worker.create_map(path, **CONFIG)
    rows = [rng.standard_normal((n, DIM)).astype(np.float32) for n in (50, 30, 40)]
    with MapStore.open(path) as store:
        store.add_sequence(rows[0], name="taken")
        with store.begin_group() as group:
            group.add(rows[1], "a")
            with pytest.raises(InputError, match="positions"):  # nothing written
                group.add(rows[2], "b", positions=np.ones((3, 2)))
            with pytest.raises(DuplicateNameError, match="two sequences of one group"):
                group.add(rows[2], "a")
            with pytest.raises(DuplicateNameError, match="other descriptors"):
                group.add(iter([rows[2][:20], rows[2][20:]]), "taken")  # hashed, not written
            with pytest.raises(EmptySequenceError):
                group.add(iter([]), "empty")
            with pytest.raises(InputError, match="thumbnails"):  # rows written, then dropped
                group.add(iter([rows[2][:35], rows[2][35:]]), "c", thumbnails=[b"x"])
            group.add(rows[0], "taken")  # a retry: committed already, writes nothing
            group.add(rows[2], None, edges=[EdgeSpec((None, 0), (1, 29), 0.5, 0)])
            results = group.commit()
        assert [(r.sequence.seq_id, r.sequence.name, r.already_committed)
                for r in results] == [(1, "a", False), (0, "taken", True), (2, "seq-2", False)]
        assert results[2].sequence.first_vertex == 80 and results[2].edges_added == 1
    final = state(path)
    assert final["stats"]["components"] == 2
    with MapStore.open(path, readonly=True) as store:
        np.testing.assert_array_equal(store.descriptors(2), rows[2])
        assert state_files(path) == {"shard-000000.f32": 64 * DIM * 4,
                                     "shard-000001.f32": 56 * DIM * 4}
