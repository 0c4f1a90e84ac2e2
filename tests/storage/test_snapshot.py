"""A pinned snapshot reads the map as of one commit, whatever the writer commits meanwhile.

In one process (the writer's own reads, as ``ingest`` and the server make them); the
real-process version, readers beside a writer that merges and removes, is
``tests/storage/test_concurrency.py::test_localize_survives_merging_ingests_and_removes``.
"""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.config import MapConfig
from sprint_map.localize.stored_view import StoredMapView
from sprint_map.storage.records import EdgeSpec
from sprint_map.storage.snapshot import MapSnapshot
from sprint_map.storage.store import MapStore

DIM = 8


def _rows(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.standard_normal((n, DIM)).astype(np.float32)


def test_a_snapshot_hides_later_commits_and_keeps_removed_sequences(tmp_path, rng):
    first = _rows(rng, 30)
    with MapStore.create(tmp_path / "m", MapConfig(dim=DIM)) as store:
        store.add_sequence(first, name="a")
        store.add_sequence(_rows(rng, 10), name="b")
        store.search(first[:1], 1)  # the index is loaded: later commits are added to it
        with MapSnapshot(store) as snap:
            # A drive on the very same places, merged into "a", then "b" removed.
            store.add_sequence(first + 1e-4, name="again",
                               edges=[EdgeSpec((None, 0), (0, 0), 0.9)])
            store.remove_sequences([1])
            assert store.index.covered == 70  # the index holds the new vertices...
            dists, ids = snap.search(first[:5] + 1e-4, 3)
            assert (ids < 40).all() and (ids >= 0).all()  # ...the snapshot never sees them
            assert ids[:, 0].tolist() == [0, 1, 2, 3, 4]
            assert snap.locate([35]) == [(1, 5)]  # removed after the snapshot: still there
            assert snap.vertices == 40 and snap.removed.count == 0
        _, now = store.search(first[:5] + 1e-4, 1)
        assert (now >= 40).all()  # a fresh search finds the newer, nearer copies
        with MapSnapshot(store) as later:
            assert later.version > snap.version and later.removed.count == 1
            _, ids = later.search(_rows(rng, 20), 5)
            assert not ((ids >= 30) & (ids < 40)).any()  # the removed "b"


def test_a_pinned_source_reads_one_snapshot_and_reports_changes(tmp_path, rng):
    with MapStore.create(tmp_path / "m", MapConfig(dim=DIM)) as store:
        store.add_sequence(_rows(rng, 10), name="a")
        store.add_sequence(_rows(rng, 10), name="b")
        source = StoredMapView(store)
        with source.pinned() as changed:
            assert not changed  # the first pin
            assert source.components_of(np.array([5, 15])).tolist() == [0, 1]
            store.add_sequence(_rows(rng, 5), name="c",
                               edges=[EdgeSpec((None, 0), (0, 1)), EdgeSpec((None, 1), (1, 1))])
            # Still the snapshot: two components, and "c" is not there.
            assert source.components_of(np.array([5, 15])).tolist() == [0, 1]
            assert source.load_component(0).seq_ids.tolist() == [0]
            assert source.vertices == 20
            with source.pinned() as nested:
                assert not nested and source.vertices == 20
        assert source.components_of(np.array([5, 15, 22])).tolist() == [0, 0, 0]
        with source.pinned() as changed:
            assert changed and source.vertices == 25
        with source.pinned() as changed:
            assert not changed
        store.remove_sequences([2])
        source.mark_current()  # the caller caught up itself (Localizer.invalidate)
        with source.pinned() as changed:
            assert not changed
            assert source.locate([15]) == [(1, 5)]


def test_visible_is_what_the_pinned_snapshot_holds(tmp_path, rng):
    with MapStore.create(tmp_path / "m", MapConfig(dim=DIM)) as store:
        store.add_sequence(_rows(rng, 10), name="a")
        store.add_sequence(_rows(rng, 10), name="b")
        source = StoredMapView(store)
        ids = np.array([5, 15, 25, -1])
        with source.pinned():
            store.remove_sequences([0])
            store.add_sequence(_rows(rng, 10), name="c")
            assert source.visible(ids).tolist() == [True, True, False, False]
        assert source.visible(ids).tolist() == [False, True, True, False]


def test_pinned_component_look_ups_follow_each_snapshot(tmp_path, rng):
    """Inside a pin the sequences already met answer from memory: the same components as a
    fresh LMDB read, in any order and repeated, and never those of an earlier snapshot after a
    merge or a removal."""
    with MapStore.create(tmp_path / "m", MapConfig(dim=DIM)) as store:
        for name, n in (("a", 10), ("b", 7), ("c", 12)):
            store.add_sequence(_rows(rng, n), name=name)
        source = StoredMapView(store)
        ids = rng.integers(0, 29, 40)
        with source.pinned():
            first = source.components_of(ids)
            again = source.components_of(ids[::-1])
        assert first.tolist() == source.components_of(ids).tolist()  # (unpinned: LMDB)
        assert again.tolist() == first[::-1].tolist()
        store.add_sequence(_rows(rng, 5), name="d",
                           edges=[EdgeSpec((None, 0), (0, 1)), EdgeSpec((None, 1), (2, 1))])
        with source.pinned():
            assert source.components_of(np.array([5, 12, 20, 30])).tolist() == [0, 1, 0, 0]
            assert source.components_of(np.array([20, 5])).tolist() == [0, 0]
        store.remove_sequences([1])
        with source.pinned():
            assert source.components_of(np.array([5, 20])).tolist() == [0, 0]
            with pytest.raises(ValueError, match="removed"):
                source.components_of(np.array([12]))
