"""``edges`` (provenance listing) and ``unmerge`` (undo one drive's merge): the edges a drive
added revoked in one commit, components rebuilt (only the affected ones) as the remaining edges
say, checked against networkx; ``check`` catching a half-done unmerge or provenance unmerge
could not trust. The CLI's JSON contracts: ``tests/cli/test_cli.py``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lmdb
import networkx as nx
import numpy as np
import pytest

from sprint_map.config import MapConfig, StoreOptions
from sprint_map.errors import ReadOnlyMapError, SprintMapError, UnknownSequenceError
from sprint_map.map import SprintMap
from sprint_map.storage.check import check_map
from sprint_map.storage.keys import EDGE_KEY, u32, u64
from sprint_map.storage.lmdb_env import MAX_DBS
from sprint_map.storage.provenance import list_edges
from sprint_map.storage.records import EdgeSpec
from sprint_map.storage.store import LMDB_DIR, MapStore
from tests.helpers import crash_worker

logical_state = crash_worker.logical_state

#: ``sprint-map edges --json``: the keys outside scripts read.
EDGE_KEYS = {"src_seq", "src_image", "dst_seq", "dst_image", "prob", "added_by"}


def random_descriptors(rng: np.random.Generator, n: int, dim: int) -> np.ndarray:
    return rng.standard_normal((n, dim)).astype(np.float32)


def build_with_provenance(make_map: Any, rng: np.random.Generator, n: int) -> Any:
    """``n`` drives; each adds edges to earlier drives (both directions), and some add
    *foreign* edges (between two earlier drives) and repeats of an existing edge (which takes
    the newer provenance): every kind of provenance ``add_sequence`` can record."""
    built = make_map.empty(MapConfig(dim=8, store=StoreOptions(shard_rows=int(rng.integers(4, 32)))))
    with MapStore.create(built.path, built.config) as store:
        for i in range(n):
            length = int(rng.integers(1, 12))
            specs: list[EdgeSpec] = []
            old = built.sequences

            def end(seq: Any) -> tuple[int, int]:
                return seq.seq_id, int(rng.integers(seq.length))

            for _ in range(int(rng.integers(0, 4)) if old else 0):
                other = end(old[int(rng.integers(len(old)))])
                new = (None, int(rng.integers(length)))
                w = float(rng.random())
                specs.append(EdgeSpec(new, other, w, new[1]))
                if rng.random() < 0.5:  # merge_both_ways: the same match in reverse
                    specs.append(EdgeSpec(other, new, w, new[1]))
            if len(old) >= 2 and rng.random() < 0.4:  # an edge between two earlier drives
                a, b = rng.choice(len(old), 2, replace=False)
                specs.append(EdgeSpec(end(old[int(a)]), end(old[int(b)]), float(rng.random())))
            if built.edge_set() and rng.random() < 0.3:  # a repeat: newer provenance
                src, dst = list(built.edge_set())[int(rng.integers(len(built.edge_set())))]
                ends = []
                for v in (src, dst):
                    seq = built.seq_of_vertex(v)
                    ends.append((seq, v - built.sequences[seq].first_vertex))
                specs.append(EdgeSpec(ends[0], ends[1], 0.5))
            built.add(store, random_descriptors(rng, length, 8), edges=specs,
                      positions=rng.uniform(0, 9, (length, 2)) if i % 2 else None)
    return built


def components_of(seqs: list[int], edges: dict[tuple[int, int], Any], built: Any
                  ) -> set[frozenset[int]]:
    graph = nx.Graph()
    graph.add_nodes_from(seqs)
    graph.add_edges_from((built.seq_of_vertex(a), built.seq_of_vertex(b)) for a, b in edges)
    return {frozenset(c) for c in nx.connected_components(graph)}


def raw_records(store: MapStore, db: str) -> dict[bytes, bytes]:
    with store.env.read() as txn:
        return {bytes(k): bytes(v) for k, v in txn.cursor(db=store.env.db(db))}


def strict_check(path: Path) -> None:
    with MapStore.open(path, readonly=True) as store:
        report = check_map(store)
    notes = [n for n in report.notes if not n.startswith("no persisted index")]
    assert report.ok and not notes, (report.violations, report.notes)


# --- unmerge against networkx ----------------------------------------------------------------


@pytest.mark.parametrize("case", range(16))
def test_unmerge_revokes_exactly_the_drives_edges_and_splits_as_networkx_says(make_map, rng,
                                                                              case):
    """Random maps with every kind of provenance; a few drives unmerged in turn. After each:
    the edges are those whose provenance is not an unmerged drive (with their provenance), the
    components those networkx finds in them, the sequences untouched bit for bit, the
    components no revoked edge was in untouched record for record, check strict."""
    n = int(rng.integers(2, 10))
    built = build_with_provenance(make_map, rng, n)
    seqs = [s.seq_id for s in built.sequences]
    expected = built.edge_set()
    with MapStore.open(built.path) as store:
        sequences_before = logical_state(store)["sequences"]
        for seq in (int(s) for s in rng.choice(n, int(rng.integers(1, n + 1)), replace=False)):
            before = components_of(seqs, expected, built)
            revoked = {k for k, v in expected.items() if v[1] == seq}
            touched = {built.seq_of_vertex(v) for k in revoked for v in k}
            affected = {c for c in before if c & touched}
            roots = {c: store.component_of(min(c)) for c in before - affected}
            uf_before = raw_records(store, "uf")

            result = store.unmerge(seq)

            expected = {k: v for k, v in expected.items() if v[1] != seq}
            after = components_of(seqs, expected, built)
            got = {(e.src, e.dst): (e.weight, e.query_seq, e.frame) for e in store.edges()}
            assert got == expected
            assert {frozenset(c.sequences) for c in store.components()} == after
            assert (result.seq_id, result.edges_removed) == (seq, len(revoked))
            parts = [c for c in after if any(c <= a for a in affected)]
            assert result.components == sorted(store.component_of(min(c)) for c in parts)
            assert store.stats() == {"sequences": n, "vertices": built.vertices,
                                     "edges": len(expected), "components": len(after)}
            for comp, root in roots.items():  # not affected: same id, same records
                assert store.component_of(min(comp)) == root
                assert all(raw_records(store, "uf")[u32(s)] == uf_before[u32(s)] for s in comp)
            for comp in store.components():
                assert comp.vertices == sum(built.sequences[s].length for s in comp.sequences)
        assert logical_state(store)["sequences"] == sequences_before
    strict_check(built.path)


def test_unmerge_keeps_later_drives_edges_and_the_old_root_keeps_its_id(make_map, rng):
    """0 <- 1 <- 2 and 3 -> 1: unmerging 1 revokes only 1's edge to 0; 2 and 3 stay joined to
    1 (their own edges). The part holding the old root keeps its id."""
    built = make_map.empty(MapConfig(dim=8, store=StoreOptions(shard_rows=8)))
    with MapStore.create(built.path, built.config) as store:
        for i in range(4):
            edges = {1: [EdgeSpec((None, 0), (0, 0)), EdgeSpec((0, 0), (None, 0))],
                     2: [EdgeSpec((None, 2), (1, 1))], 3: [EdgeSpec((None, 1), (1, 2))]}
            built.add(store, random_descriptors(rng, 5, 8), edges=edges.get(i, []))
        (root,) = [c.component for c in store.components()]
        result = store.unmerge(1)
        assert result.edges_removed == 2
        assert {frozenset(c.sequences) for c in store.components()} == {
            frozenset({0}), frozenset({1, 2, 3})}
        assert root in result.components and sorted(result.components) == result.components
        assert len(result.components) == 2
        assert store.component_of(0 if root == 0 else 1) == root
        assert {(e.src_seq, e.dst_seq, e.added_by) for e in list_edges(store)} == {
            (2, 1, 2), (3, 1, 3)}
    strict_check(built.path)


def test_unmerge_is_idempotent_and_a_drive_without_edges_is_a_no_op(make_map):
    built = make_map((5, 6, 7, 8), edges=2)
    with MapStore.open(built.path) as store:
        first = store.unmerge(2)
        assert first.edges_removed == 2
        state = logical_state(store)
        records = {db: raw_records(store, db) for db in ("edges", "edges_rev", "uf", "members",
                                                         "comp", "meta")}
        for seq in (2, 0):  # again; the first drive added nothing
            again = store.unmerge(seq)
            assert again.to_dict() == {"seq_id": seq, "edges_removed": 0, "components": []}
            assert logical_state(store) == state
            assert {db: raw_records(store, db) for db in records} == records
    strict_check(built.path)


def test_unknown_sequence_changes_nothing(make_map):
    built = make_map((5, 6, 7), edges=2)
    with SprintMap.open(built.path) as m:
        before = logical_state(m.store)
        for ref in (9, "no such drive", -1):
            with pytest.raises(UnknownSequenceError):
                m.unmerge(ref)
            with pytest.raises(UnknownSequenceError):
                m.edges(ref)
            with pytest.raises(UnknownSequenceError):
                m.edges(added_by=ref)
        assert logical_state(m.store) == before
        m.remove_sequences([1])
        with pytest.raises(UnknownSequenceError, match="no sequence 1"):
            m.unmerge(1)  # a removed drive's edges went with it
    with SprintMap.open(built.path, readonly=True) as m, pytest.raises(ReadOnlyMapError):
        m.unmerge(2)
    strict_check(built.path)


def test_unmerge_waits_for_a_sequence_being_written(make_map, rng):
    built = make_map((5, 6), edges=1)
    with MapStore.open(built.path) as store, store.begin_sequence("w") as writer:
        writer.append(random_descriptors(rng, 3, 8))
        with pytest.raises(SprintMapError, match="being written"):
            store.unmerge(1)
        writer.commit()


def test_unmerge_by_name_through_the_facade_after_a_compaction(make_map, rng):
    """Vertex ids are renumbered by ``compact``: provenance survives it and unmerge still finds
    a drive's edges (its scan bound rests on vertex order = commit order, which compact keeps)."""
    built = build_with_provenance(make_map, rng, 8)
    with SprintMap.open(built.path) as m:
        m.remove_sequences([0])
        listed = [e.to_dict() for e in m.edges()]
        m.compact()
        assert [e.to_dict() for e in m.edges()] == listed
        for seq in range(1, 8):
            want = [e for e in listed if e["added_by"] == seq]
            assert [e.to_dict() for e in m.edges(added_by=built.sequences[seq].name)] == want
            assert m.unmerge(built.sequences[seq].name).edges_removed == len(want)
        assert m.edges() == [] and m.stats()["components"] == 7
    strict_check(built.path)


# --- edges: the listing -------------------------------------------------------------------------


def test_edges_lists_provenance_and_filters(make_map, rng):
    built = build_with_provenance(make_map, rng, 7)

    def seq_image(v: int) -> tuple[int, int]:
        seq = built.seq_of_vertex(v)
        return seq, v - built.sequences[seq].first_vertex

    want = [{"src_seq": seq_image(s)[0], "src_image": seq_image(s)[1],
             "dst_seq": seq_image(d)[0], "dst_image": seq_image(d)[1],
             "prob": w, "added_by": q, "frame": f}
            for (s, d), (w, q, f) in sorted(built.edge_set().items())]
    with SprintMap.open(built.path, readonly=True) as m:
        got = m.edges()
        assert [{**e.to_dict(), "frame": e.frame} for e in got] == want
        assert all(set(e.to_dict()) == EDGE_KEYS for e in got)
        for seq in range(7):
            touching = [w for w in want if seq in (w["src_seq"], w["dst_seq"])]
            assert [{**e.to_dict(), "frame": e.frame} for e in m.edges(seq)] == touching
            assert m.edges(built.sequences[seq].name) == m.edges(seq)
            added = [w for w in want if w["added_by"] == seq]
            assert [{**e.to_dict(), "frame": e.frame} for e in m.edges(added_by=seq)] == added
            both = [w for w in touching if w["added_by"] == seq]
            assert [{**e.to_dict(), "frame": e.frame}
                    for e in m.edges(seq, added_by=seq)] == both


def test_a_schema_1_map_lists_its_provenance(make_map):
    """Provenance is in every edge value since schema 1: an old map lists it read-only and is
    unmerged after the writer's upgrade."""
    built = make_map((5, 6, 7), edges=2)
    env = lmdb.open(str(built.path / LMDB_DIR), max_dbs=MAX_DBS)
    with env.begin(write=True) as txn:
        txn.drop(env.open_db(b"removed", txn=txn), delete=True)
        txn.put(b"schema_version", b"1", db=env.open_db(b"meta", txn=txn))
    env.close()
    with SprintMap.open(built.path, readonly=True) as m:
        assert m.info()["schema_version"] == 1
        assert sorted(e.added_by for e in m.edges()) == [1, 1, 2, 2]
    with SprintMap.open(built.path) as m:
        assert m.unmerge(2).edges_removed == 2
    strict_check(built.path)


# --- check catches a half-done unmerge -------------------------------------------------------


def _half_unmerge(store: MapStore, step: str) -> None:
    """Revoke sequence 2's edges as a broken unmerge would: ``step`` says where it stops."""
    revoked = [(r.src, r.dst) for r in store.edges() if r.query_seq == 2]
    db = store.env.db

    def body(txn: lmdb.Transaction) -> None:
        for src, dst in revoked:
            txn.delete(EDGE_KEY.pack(src, dst), db=db("edges"))
            if step != "reverse index left":
                txn.delete(EDGE_KEY.pack(dst, src), db=db("edges_rev"))
        if step != "counter left":
            n = int.from_bytes(txn.get(b"n_edges", db=db("meta")), "big")
            txn.put(b"n_edges", u64(n - len(revoked)), db=db("meta"))

    assert revoked
    store.env.write(body)


@pytest.mark.parametrize(("step", "area"), [("reverse index left", "edge_index"),
                                            ("counter left", "edge_index"),
                                            ("components left", "components")])
def test_check_catches_a_half_done_unmerge(make_map, rng, step, area):
    """Edges revoked but not their reverse entries, or not the edge counter, or the components
    not rebuilt (drive 2 is the only link of 0 and 2): each is a violation."""
    built = make_map.empty(MapConfig(dim=8, store=StoreOptions(shard_rows=8)))
    with MapStore.create(built.path, built.config) as store:
        for i in range(3):
            edges = {1: [EdgeSpec((None, 0), (0, 0))], 2: [EdgeSpec((None, 1), (0, 1)),
                                                           EdgeSpec((0, 1), (None, 1))]}
            built.add(store, random_descriptors(rng, 4, 8), edges=edges.get(i, []))
        _half_unmerge(store, step)
    with MapStore.open(built.path, readonly=True) as store:
        report = check_map(store)
    assert area in report.areas, report.violations


def test_ingest_then_unmerge_gives_back_the_components_before_the_drive(tmp_path, rng):
    """Real localisation edges: three drives of one road ingested, the third unmerged: the
    components are those before it came, plus the drive alone; its edges all touched it."""
    dim, n = 16, 60
    road = np.cumsum(rng.standard_normal((n, dim)).astype(np.float32), axis=0) * 0.3

    def drive() -> np.ndarray:
        return road + np.float32(0.5) * rng.standard_normal((n, dim)).astype(np.float32)

    with SprintMap.create(tmp_path / "m", MapConfig(dim=dim)) as m:
        m.ingest(drive(), name="d0")
        m.ingest(drive(), name="d1")
        before = {frozenset(c.sequences) for c in m.components()}
        added = m.ingest(drive(), name="d2").added.edges_added
        assert added > 0
        mine = m.edges(added_by="d2")
        assert len(mine) == added and all(2 in (e.src_seq, e.dst_seq) for e in mine)
        assert m.unmerge("d2").edges_removed == added
        assert {frozenset(c.sequences) for c in m.components()} == before | {frozenset({2})}
        assert m.edges("d2") == []
    strict_check(tmp_path / "m")


def _set_provenance(store: MapStore, key: tuple[int, int], value: bytes | int) -> None:
    def body(txn: lmdb.Transaction) -> None:
        db = store.env.db("edges")
        raw = bytearray(txn.get(EDGE_KEY.pack(*key), db=db))
        if isinstance(value, bytes):
            raw = bytearray(value)
        else:
            raw[8:12] = u32(value)
        txn.put(EDGE_KEY.pack(*key), bytes(raw), db=db)

    store.env.write(body)


@pytest.mark.parametrize(("value", "message"), [
    (1, "joins sequence 2, newer than sequence 1 that added it"),
    (99, "was added by sequence 99, beyond next_seq_id 3"),
    (b"\0" * 7, "has a malformed value"),
])
def test_check_catches_provenance_unmerge_could_not_trust(make_map, rng, value, message):
    """``unmerge`` finds a drive's edges by one range scan up to the drive's last vertex: an
    edge must be added by a drive no older than its ends, below next_seq_id."""
    built = make_map.empty(MapConfig(dim=8, store=StoreOptions(shard_rows=8)))
    with MapStore.create(built.path, built.config) as store:
        for i in range(3):
            built.add(store, random_descriptors(rng, 4, 8),
                      edges=[EdgeSpec((None, 0), (0, 1))] if i == 2 else [])
        (edge,) = built.edge_set()
        _set_provenance(store, edge, value)
    with MapStore.open(built.path, readonly=True) as store:
        report = check_map(store)
    assert report.areas == {"edges"}, report.violations
    assert [v for v in report.violations if message in v], report.violations


def test_check_catches_sequence_ids_out_of_vertex_order(make_map, rng):
    """Sequence ids follow vertex order (both follow commits): two records swapped are caught."""
    from sprint_map.storage.records import SequenceRecord

    built = make_map((5, 5, 3), edges=0)
    with MapStore.open(built.path) as store:
        a, b = store.sequence(0), store.sequence(1)

        def body(txn: lmdb.Transaction) -> None:
            db = store.env.db
            for rec, first in ((a, b.first_vertex), (b, a.first_vertex)):
                moved = SequenceRecord(rec.seq_id, rec.name, rec.length, first, rec.created,
                                       rec.source)
                txn.put(u32(rec.seq_id), moved.encode(), db=db("sequences"))
                txn.put(u64(moved.last_vertex), u32(rec.seq_id), db=db("vrange"))

        store.env.write(body)
    with MapStore.open(built.path, readonly=True) as store:
        report = check_map(store)
    assert any("lies after sequence 1 in vertex order" in v for v in report.violations), \
        report.violations
