"""``remove``: sequences retired in one commit, components split as the remaining edges say,
searches that never return a removed vertex, and check/repair of the removed ranges."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lmdb
import networkx as nx
import numpy as np
import pytest

from sprint_map.config import SCHEMA_VERSION, MapConfig, StoreOptions
from sprint_map.errors import UnknownSequenceError
from sprint_map.localize.stored_view import StoredMapView
from sprint_map.map import SprintMap
from sprint_map.storage.check import check_map
from sprint_map.storage.keys import u64
from sprint_map.storage.lmdb_env import MAX_DBS
from sprint_map.storage.records import EdgeSpec
from sprint_map.storage.repair import repair_map
from sprint_map.storage.store import LMDB_DIR, MapStore
from tests.helpers import crash_worker

logical_state = crash_worker.logical_state


def random_descriptors(rng: np.random.Generator, n: int, dim: int) -> np.ndarray:
    return rng.standard_normal((n, dim)).astype(np.float32)


def expected_after(built: Any, removed: set[int]) -> tuple[dict, set[frozenset[int]]]:
    """Edges between surviving sequences (with provenance) and their networkx components."""
    edges = {k: v for k, v in built.edge_set().items()
             if built.seq_of_vertex(k[0]) not in removed
             and built.seq_of_vertex(k[1]) not in removed}
    graph = nx.Graph()
    graph.add_nodes_from(s.seq_id for s in built.sequences if s.seq_id not in removed)
    graph.add_edges_from((built.seq_of_vertex(a), built.seq_of_vertex(b)) for a, b in edges)
    return edges, {frozenset(c) for c in nx.connected_components(graph)}


def strict_check(path: Path) -> None:
    """``check`` passes with no note but a missing index (a map never searched has none)."""
    with MapStore.open(path, readonly=True) as store:
        report = check_map(store)
    notes = [n for n in report.notes if not n.startswith("no persisted index")]
    assert report.ok and not notes, (report.violations, report.notes)


@pytest.mark.parametrize("case", range(12))
def test_removal_splits_components_as_the_remaining_edges_do(make_map, rng, case):
    """Random maps (chains, stars, dense webs of edges), random removals: the components are
    those networkx finds in the edges that are left; survivors are untouched, bit for bit."""
    n = int(rng.integers(3, 12))
    built = make_map([int(x) for x in rng.integers(1, 25, n)], edges=int(rng.integers(0, 4)),
                    shard_rows=int(rng.integers(4, 40)))
    removed = {int(s) for s in rng.choice(n, int(rng.integers(1, n)), replace=False)}
    with MapStore.open(built.path) as store:
        result = store.remove_sequences(sorted(removed))
    edges, components = expected_after(built, removed)
    with MapStore.open(built.path, readonly=True) as store:
        assert {frozenset(c.sequences) for c in store.components()} == components
        got = {(e.src, e.dst): (e.weight, e.query_seq, e.frame) for e in store.edges()}
        assert got == edges
        assert store.stats() == {"sequences": n - len(removed),
                                 "vertices": built.vertices,  # ids stay until compact
                                 "edges": len(edges), "components": len(components)}
        for comp in store.components():
            assert comp.vertices == sum(built.sequences[s].length for s in comp.sequences)
            assert all(store.component_of(s) == comp.component for s in comp.sequences)
        for seq in built.sequences:
            if seq.seq_id in removed:
                with pytest.raises(UnknownSequenceError):
                    store.sequence(seq.seq_id)
                with pytest.raises(UnknownSequenceError):
                    store.sequence_by_name(seq.name)
                with pytest.raises(UnknownSequenceError):
                    store.locate([seq.first_vertex])
                continue
            assert store.descriptors(seq.seq_id).tobytes() == seq.descriptors.tobytes()
            pos = store.positions(seq.seq_id)
            assert (pos is None) == (seq.positions is None)
            if pos is not None:
                np.testing.assert_array_equal(pos, seq.positions)
        assert store.removed_vertices() == sum(built.sequences[s].length for s in removed)
    assert {r.seq_id for r in result.removed} == removed
    assert result.edges_removed == len(built.edge_set()) - len(edges)
    strict_check(built.path)


def test_a_bridge_removed_splits_its_component_and_ids_follow_the_roots(make_map, rng):
    """0 - 1 - 2 and 3 - 1: removing the bridge 1 leaves three components; the part holding
    the old root keeps its id."""
    built = make_map.empty(MapConfig(dim=8, store=StoreOptions(shard_rows=8)))
    with MapStore.create(built.path, built.config) as store:
        for i in range(4):
            edges = {1: [EdgeSpec((None, 0), (0, 0))], 2: [EdgeSpec((1, 1), (None, 2))],
                     3: [EdgeSpec((None, 1), (1, 2))]}.get(i, [])
            built.add(store, random_descriptors(rng, 5, 8), edges=edges)
        (root,) = [c.component for c in store.components()]
        result = store.remove_sequences([1])
        assert result.components_affected == [root]
        assert {frozenset(c.sequences) for c in store.components()} == {
            frozenset({0}), frozenset({2}), frozenset({3})}
        assert root in result.components_after and store.component_of(root) == root
        assert store.stats()["edges"] == 0 and result.edges_removed == 3
    strict_check(built.path)


def _near_copies(rng: np.random.Generator, dim: int) -> tuple[np.ndarray, np.ndarray]:
    base = random_descriptors(rng, 30, dim)
    return base, base + np.float32(1e-3) * random_descriptors(rng, 30, dim)


@pytest.mark.parametrize("k", [1, 5, 40])
def test_search_never_returns_removed_vertices_and_still_finds_k(tmp_path, rng, k):
    """Each live row has a removed near-copy closer than any live row: the search must skip
    them all and return the exact k nearest live vertices (brute force over the live rows)."""
    dim = 16
    with MapStore.create(tmp_path / "m", MapConfig(dim=dim, store=StoreOptions(shard_rows=16))) as store:
        live_rows, copies = _near_copies(rng, dim)
        store.add_sequence(copies, name="stale-a")
        store.add_sequence(live_rows, name="live")
        store.add_sequence(copies + 1e-3, name="stale-b")
        store.add_sequence(random_descriptors(rng, 20, dim), name="other")
        store.remove_sequences([0, 2])
        live = np.r_[30:60, 90:110]
        rows = store.shards.rows(0, 110, 110)
        for queries in (live_rows, copies):  # the removed rows themselves as queries too
            dists, ids = store.search(queries, k)
            want = min(k, len(live))
            assert (ids[:, :want] >= 0).all() and (ids[:, want:] == -1).all()
            assert np.isin(ids[:, :want], live).all()
            exact = ((queries[:, None, :] - rows[None, live, :]) ** 2).sum(-1)
            best = live[np.argsort(exact, axis=1, kind="stable")[:, :want]]
            assert (np.sort(ids[:, :want], 1) == np.sort(best, 1)).all()
            np.testing.assert_allclose(dists[:, :want], np.sort(exact, 1)[:, :want], rtol=1e-4,
                                       atol=1e-5)


def test_the_hmm_never_sees_a_removed_sequence(make_map, rng):
    built = make_map((10, 10, 10), edges=3)
    with MapStore.open(built.path) as store:
        store.add_sequence(random_descriptors(rng, 10, 8), edges=[
            EdgeSpec((None, 0), (0, 1)), EdgeSpec((None, 1), (1, 1)), EdgeSpec((2, 3), (None, 4))])
        store.remove_sequences([1])
        source = StoredMapView(store)
        with pytest.raises(ValueError, match="removed"):
            source.components_of(np.array([10]))
        for comp in store.components():
            graph = source.load_component(comp.component)
            assert 1 not in graph.seq_ids.tolist()
            inside = [(a <= v < a + n) for v in np.r_[graph.edge_src, graph.edge_dst]
                      for a, n in zip(graph.seq_first, graph.seq_len, strict=True)]
            assert np.asarray(inside).reshape(-1, len(graph.seq_ids)).any(1).all()


def test_localisation_after_removal_uses_the_remaining_drives(tmp_path, rng):
    """Three drives of one road; the first is forgotten: a new drive is still localised, now
    on the drives that remain, at the right places."""
    dim, n = 32, 200
    road = np.cumsum(rng.standard_normal((n, dim)).astype(np.float32), axis=0) * 0.3

    def drive() -> np.ndarray:
        return road + np.float32(0.6) * rng.standard_normal((n, dim)).astype(np.float32)

    with SprintMap.create(tmp_path / "m", MapConfig(dim=dim)) as m:
        for i in range(3):
            m.ingest(drive(), name=f"d{i}")
        assert len(m.components()) == 1
        m.remove_sequences(["d0"])
        decisions, _ = m.localize(drive())
    matched = [d for d in decisions if d.is_match]
    assert len(matched) > 0.8 * n
    assert {d.seq_id for d in matched} <= {1, 2}
    assert np.mean([abs(d.image_id - d.frame) <= 2 for d in matched]) > 0.9


def test_a_failed_removal_changes_nothing(make_map):
    built = make_map((5, 6, 7), edges=2)
    with MapStore.open(built.path) as store:
        before = logical_state(store)
        with pytest.raises(UnknownSequenceError):
            store.remove_sequences([0, 9])
        assert logical_state(store) == before
        assert store.removed_vertices() == 0


def test_sequences_added_after_a_removal_continue_the_ids(make_map, rng):
    built = make_map((5, 6, 7), edges=2)
    with MapStore.open(built.path) as store:
        store.remove_sequences([1])
        name = built.sequences[1].name  # a removed sequence's name is free again
        added = store.add_sequence(random_descriptors(rng, 4, 8), name=name,
                                   edges=[EdgeSpec((None, 0), (2, 3))]).sequence
        assert (added.seq_id, added.first_vertex) == (3, 18)
        _, ids = store.search(store.descriptors(3), 1)
        assert ids[:, 0].tolist() == [18, 19, 20, 21]
    strict_check(built.path)


def test_check_and_repair_of_the_removed_records(make_map):
    built = make_map((5, 6, 7), edges=0, positions=True)
    with MapStore.open(built.path) as store:
        store.remove_sequences([1])
        db = store.env.db

        def corrupt(txn: lmdb.Transaction) -> None:
            txn.put(b"removed_vertices", u64(99), db=db("meta"))
            txn.put(u64(7), b"\0" * 32, db=db("vertex_data"))  # a position in the hole

        store.env.write(corrupt)
    with MapStore.open(built.path, readonly=True) as store:
        report = check_map(store)
    assert report.areas == {"removed"}
    assert len(report.violations) == 2
    fixed = repair_map(built.path)
    assert fixed.ok, fixed.to_dict()
    strict_check(built.path)
    with MapStore.open(built.path) as store:  # a removed range overlapping a live sequence
        store.env.write(lambda txn: txn.put(u64(12), u64(0) + b"\0\0\0\1",
                                            db=store.env.db("removed")))
    with MapStore.open(built.path, readonly=True) as store:
        assert "sequences" in check_map(store).areas


def test_a_schema_1_map_is_read_as_it_is_and_upgraded_by_a_writer(make_map):
    built = make_map((5, 6), edges=1)
    env = lmdb.open(str(built.path / LMDB_DIR), max_dbs=MAX_DBS)  # make it a schema-1 map
    with env.begin(write=True) as txn:
        txn.drop(env.open_db(b"removed", txn=txn), delete=True)
        txn.put(b"schema_version", b"1", db=env.open_db(b"meta", txn=txn))
    env.close()
    with SprintMap.open(built.path, readonly=True) as m:
        assert m.info()["schema_version"] == 1 and m.check().ok
        assert m.search(built.all_descriptors(), 1)[1][:, 0].tolist() == list(range(11))
    with SprintMap.open(built.path) as m:
        assert f"upgraded the map from schema version 1 to {SCHEMA_VERSION}" in m.store.recovery
        m.remove_sequences([0])
    with SprintMap.open(built.path, readonly=True) as m:
        assert m.info()["schema_version"] == SCHEMA_VERSION and m.check().ok
