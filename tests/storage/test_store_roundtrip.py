"""Round trips through the store: what is added comes back bit for bit after close and reopen."""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.config import MapConfig, StoreOptions
from sprint_map.errors import MapCorruptError
from sprint_map.storage.check import check_map
from sprint_map.storage.index.map_index import index_files
from sprint_map.storage.keys import EDGE_KEY, EDGE_VAL
from sprint_map.storage.records import EdgeSpec, EdgeTable
from sprint_map.storage.store import INDEX_DIR, SHARDS_DIR, MapStore

# Lengths around shard_rows=16: single frames, exact fills, spans over two and three shards.
LENGTH_SETS = {
    "small": (1, 2, 3),
    "exact-shards": (16, 16, 16),
    "spanning": (15, 2, 17, 40, 1, 33),
    "one-big": (100,),
}


@pytest.mark.parametrize("lengths", LENGTH_SETS.values(), ids=LENGTH_SETS.keys())
@pytest.mark.parametrize("positions", [True, False, "alternate"])
@pytest.mark.parametrize("readonly", [True, False], ids=["reader", "writer"])
def test_reopen_is_bit_identical(make_map, expect_map, lengths, positions, readonly):
    built = make_map(lengths, positions=positions, edges=2)
    with MapStore.open(built.path, readonly=readonly) as store:
        expect_map(store, built)
    with MapStore.open(built.path, readonly=True) as store:
        expect_map(store, built)  # and again after the writer's close (index persisted)
        report = check_map(store)
        assert report.ok, report.violations


def test_shard_files_hold_exactly_the_committed_rows(make_map):
    built = make_map((15, 2, 17, 40), shard_rows=16, dim=4)
    shard_dir = built.path / SHARDS_DIR
    sizes = sorted((p.name, p.stat().st_size) for p in shard_dir.iterdir())
    # 74 rows of 16 bytes: four full shards and 10 rows in the fifth.
    assert sizes == [(f"shard-{i:06d}.f32", 16 * 16) for i in range(4)] + [
        ("shard-000004.f32", 10 * 16)
    ]
    raw = np.concatenate([np.fromfile(shard_dir / n, dtype="<f4") for n, _ in sizes])
    assert raw.tobytes() == built.all_descriptors().tobytes()


def test_descriptors_of_other_dtypes_are_stored_as_float32(tmp_path, rng):
    with MapStore.create(tmp_path / "m", MapConfig(dim=3, store=StoreOptions(shard_rows=4))) as store:
        f64 = rng.standard_normal((5, 3))
        ints = rng.integers(-100, 100, (3, 3), dtype=np.int64)
        lists = [[0.5, 1.5, -2.0]]
        for data in (f64, ints, lists):
            store.add_sequence(data)
    with MapStore.open(tmp_path / "m", readonly=True) as store:
        for seq_id, data in enumerate((f64, ints, lists)):
            want = np.asarray(data, dtype=np.float32)
            assert store.descriptors(seq_id).tobytes() == want.tobytes()


def test_default_names_sources_and_lookups(tmp_path, rng):
    with MapStore.create(tmp_path / "m", MapConfig(dim=2, store=StoreOptions(shard_rows=3))) as store:
        a = store.add_sequence(rng.standard_normal((4, 2)))
        b = store.add_sequence(rng.standard_normal((5, 2)), name="monday", source="cam0")
        c = store.add_sequence(rng.standard_normal((1, 2)))
    assert [r.sequence.name for r in (a, b, c)] == ["seq-0", "monday", "seq-2"]
    with MapStore.open(tmp_path / "m", readonly=True) as store:
        assert store.sequence_by_name("monday").source == "cam0"
        assert store.locate([0, 3, 4, 8, 9]) == [(0, 0), (0, 3), (1, 0), (1, 4), (2, 0)]
        assert [store.vertex_id(1, i) for i in range(5)] == [4, 5, 6, 7, 8]


def test_edges_keep_provenance_and_repeats_keep_the_newest(tmp_path, rng):
    cfg = MapConfig(dim=2, store=StoreOptions(shard_rows=4))
    with MapStore.create(tmp_path / "m", cfg) as store:
        store.add_sequence(rng.standard_normal((3, 2)))
        first = store.add_sequence(
            rng.standard_normal((3, 2)),
            edges=[EdgeSpec((None, 1), (0, 2), weight=0.25, frame=1),
                   EdgeSpec((0, 0), (None, 0), weight=0.75)],
        )
        assert first.edges_added == 2
        again = store.add_sequence(
            rng.standard_normal((2, 2)),
            edges=[EdgeSpec((1, 1), (0, 2), weight=0.5, frame=0),  # repeat: newer provenance
                   EdgeSpec((None, 1), (1, 0), weight=1.0, frame=1)],
        )
        assert again.edges_added == 1
    with MapStore.open(tmp_path / "m", readonly=True) as store:
        edges = {(e.src, e.dst): e for e in store.edges()}
        assert set(edges) == {(4, 2), (0, 3), (7, 3)}
        assert (edges[(4, 2)].weight, edges[(4, 2)].query_seq, edges[(4, 2)].frame) == (0.5, 2, 0)
        assert (edges[(0, 3)].weight, edges[(0, 3)].query_seq, edges[(0, 3)].frame) == (
            0.75, 1, None)
        assert [e.dst for e in store.edges_from(3, 5)] == [2]
        with store.env.read() as txn:
            for ranges in ([(3, 5)], [(0, 0), (6, 7)], [(0, 9)], [(1, 2), (8, 9)], []):
                table = store.edge_table_from(ranges, txn)
                records = [e for a, b in ranges for e in store.edges_from(a, b, txn)]
                assert list(zip(table.src.tolist(), table.dst.tolist(), table.prob.tolist(),
                                table.added_by.tolist(), strict=True)) == [
                    (e.src, e.dst, e.weight, -1 if e.query_seq is None else e.query_seq)
                    for e in records]
        assert store.stats()["edges"] == 3


@pytest.mark.parametrize("cut", ["key", "value"])
def test_an_edge_table_refuses_a_record_of_the_wrong_size(cut):
    key, value = EDGE_KEY.pack(3, 4), EDGE_VAL.pack(0.5, 1, 2, 0.0)
    keys, values = [key, key], [value, value]
    assert len(EdgeTable.decode(keys, values)) == 2
    if cut == "key":
        keys[1] = key[:-1]
    else:
        values[1] = value + b"x"
    with pytest.raises(MapCorruptError, match="corrupt edge record"):
        EdgeTable.decode(keys, values)


@pytest.mark.parametrize("readonly", [True, False], ids=["reader", "writer"])
def test_each_vector_is_its_own_nearest_neighbour(make_map, readonly):
    built = make_map((7, 16, 25, 3), dim=16, shard_rows=16)
    everything = built.all_descriptors()
    with MapStore.open(built.path, readonly=readonly) as store:
        distances, ids = store.search(everything, k=3)
    np.testing.assert_array_equal(ids[:, 0], np.arange(len(everything)))
    assert (distances[:, 0] == 0).all()
    assert (distances[:, 1] > 0).all()  # and nothing else is at distance 0


def test_search_pads_with_minus_one_when_k_exceeds_the_map(make_map):
    built = make_map((2, 1), dim=4)
    with MapStore.open(built.path, readonly=True) as store:
        _, ids = store.search(built.all_descriptors()[:1], k=5)
    assert ids[0, 0] == 0
    assert sorted(ids[0, 1:3].tolist()) == [1, 2]
    assert ids[0, 3:].tolist() == [-1, -1]


def _index_stamps(path):
    return [upto for upto, _ in index_files(path / INDEX_DIR)]


def test_index_is_persisted_on_close_and_reloaded_as_is(make_map):
    built = make_map((10, 20, 5), dim=8)
    with MapStore.open(built.path) as store:
        store.search(built.all_descriptors()[:1], k=1)  # load (rebuild: nothing persisted yet)
        assert store.index.events == ["index rebuilt from the shards (35 vertices)"]
    assert _index_stamps(built.path) == [35]
    with MapStore.open(built.path, readonly=True) as store:
        _, ids = store.search(built.all_descriptors(), k=1)
        assert store.index.events == []
        assert store.index.persisted == 35
    np.testing.assert_array_equal(ids[:, 0], np.arange(35))


def test_index_persisted_every_n_vertices_while_adding(tmp_path, rng):
    cfg = MapConfig(dim=4, store=StoreOptions(shard_rows=8, index_persist_every=10))
    with MapStore.create(tmp_path / "m", cfg) as store:
        stamps = []
        for length in (4, 4, 4, 9, 1, 12):
            store.add_sequence(rng.standard_normal((length, 4)))
            stamps.append(_index_stamps(tmp_path / "m"))
    # A persist happens once the vertices added since the last file reach both 10 and that
    # file's size (geometric, so rewriting the whole file stays linear overall); one file is kept.
    assert stamps == [[], [], [12], [12], [12], [34]]


def test_lagging_index_is_caught_up_from_the_shards(make_map, monkeypatch):
    built = make_map((10, 20), dim=8)
    with MapStore.open(built.path) as store:
        store.search(built.all_descriptors()[:1], k=1)
        store.flush()
        make_map.add_random(store, built, 17, index=2)
        make_map.add_random(store, built, 3, index=3)
        # Stand-in for a writer killed before its next persist (the crash tests do it for real).
        monkeypatch.setattr(store.index, "persist", lambda: False)
    monkeypatch.undo()
    assert _index_stamps(built.path) == [30]
    for readonly in (True, False):
        with MapStore.open(built.path, readonly=readonly) as store:
            _, ids = store.search(built.all_descriptors(), k=1)
            assert store.index.persisted == 30
            assert store.index.covered == 50
            np.testing.assert_array_equal(ids[:, 0], np.arange(50))
    assert _index_stamps(built.path) == [50]  # the writer persisted the caught-up index


def test_missing_index_is_rebuilt(make_map):
    built = make_map((10, 20, 6), dim=8)
    with MapStore.open(built.path) as store:
        store.search(built.all_descriptors()[:1], k=1)
    for _, path in index_files(built.path / INDEX_DIR):
        path.unlink()
    with MapStore.open(built.path, readonly=True) as store:
        _, ids = store.search(built.all_descriptors(), k=1)
        assert store.index.events == ["index rebuilt from the shards (36 vertices)"]
    np.testing.assert_array_equal(ids[:, 0], np.arange(36))


def test_reader_search_sees_rows_added_after_it_loaded(make_map):
    """A loaded index catches up with later commits (here: a later session of the same process)."""
    built = make_map((5,), dim=4)
    with MapStore.open(built.path) as store:
        store.search(built.all_descriptors()[:1], k=1)
        make_map.add_random(store, built, 6, index=1)
        _, ids = store.search(built.all_descriptors(), k=1)
    np.testing.assert_array_equal(ids[:, 0], np.arange(11))


def test_lmdb_map_grows_when_full(make_map, rng, expect_map):
    """Positions fill a 1 MiB LMDB: the write is retried on a doubled map, nothing is lost."""
    cfg = MapConfig(dim=1, store=StoreOptions(shard_rows=4096, initial_map_size=1 << 20))
    built = make_map.empty(cfg)
    with MapStore.create(built.path, cfg) as store:
        for _ in range(6):
            n = 4000
            built.add(store, rng.standard_normal((n, 1)), positions=rng.standard_normal((n, 4)))
        grown = store.env.map_size()
    assert grown > 1 << 20
    with MapStore.open(built.path, readonly=True) as store:
        expect_map(store, built)
