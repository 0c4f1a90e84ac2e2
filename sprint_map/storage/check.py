"""Full consistency check of a map against every invariant of the on-disk format.

Run on a map opened read-only, so that nothing the writer's open would silently repair is hidden.
Complexity: O(sequences + edges + shards) LMDB reads, plus reading the persisted index file once
and comparing a sample of its vectors with the shards.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import faiss
import networkx as nx
import numpy as np

from sprint_map.errors import StorageIOError
from sprint_map.storage.atomic import PARTIAL_SUFFIX
from sprint_map.storage.index_store import index_files
from sprint_map.storage.keys import (
    COMP_VAL,
    EDGE_KEY,
    UF_VAL,
    SequenceRecord,
    read_u32,
    read_u64,
)
from sprint_map.storage.store import COUNTERS, INDEX_DIR, SHARDS_DIR, MapStore
from sprint_map.storage.union_find import MEMBER_KEY

#: Index vectors compared bit for bit with their shard rows.
INDEX_SAMPLE = 32


@dataclass
class CheckReport:
    """Result of :func:`check_map`: ``ok`` when ``violations`` is empty."""

    violations: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    checked: dict[str, int] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.violations

    def to_dict(self) -> dict[str, Any]:
        return {"ok": self.ok, "violations": self.violations, "notes": self.notes,
                "checked": self.checked}


def check_map(store: MapStore, *, seed: int = 0) -> CheckReport:
    """Verify every invariant of ``store``; see ``docs/architecture.md``, "Invariants"."""
    report = CheckReport()
    bad = report.violations.append
    env = store.env
    with env.read() as txn:
        counters = {name: store.counter(name, txn) for name in COUNTERS}
        seqs = [SequenceRecord.decode(v) for _, v in txn.cursor(db=env.db("sequences"))]
        names = {bytes(k).decode(): read_u32(v) for k, v in txn.cursor(db=env.db("seq_names"))}
        vrange = {read_u64(k): read_u32(v) for k, v in txn.cursor(db=env.db("vrange"))}
        shard_rows = {read_u32(k): read_u64(v) for k, v in txn.cursor(db=env.db("shards"))}
        edges = [EDGE_KEY.unpack(k) for k in txn.cursor(db=env.db("edges")).iternext(values=False)]
        rev = [EDGE_KEY.unpack(k) for k in txn.cursor(db=env.db("edges_rev")).iternext(values=False)]
        uf = {read_u32(k): UF_VAL.unpack(v) for k, v in txn.cursor(db=env.db("uf"))}
        members = [MEMBER_KEY.unpack(k) for k in txn.cursor(db=env.db("members")).iternext(values=False)]
        comp = {read_u32(k): COMP_VAL.unpack(v) for k, v in txn.cursor(db=env.db("comp"))}
    total = counters["next_vertex_id"]
    report.checked.update(sequences=len(seqs), vertices=total, edges=len(edges))

    # Sequences, names and dense vertex ranges: (seq, image) <-> vertex is one-to-one exactly
    # when the ranges tile 0..total-1 with no gap or overlap.
    if counters["n_sequences"] != len(seqs):
        bad(f"meta says {counters['n_sequences']} sequences, found {len(seqs)}")
    expected = 0
    by_id = {s.seq_id: s for s in seqs}
    for seq in sorted(seqs, key=lambda s: s.first_vertex):
        if seq.length < 1:
            bad(f"sequence {seq.seq_id} is empty")
        if seq.first_vertex != expected:
            bad(f"sequence {seq.seq_id} starts at vertex {seq.first_vertex}, expected {expected}")
        expected = seq.first_vertex + seq.length
        if vrange.get(seq.last_vertex) != seq.seq_id:
            bad(f"vertex range index has no entry for sequence {seq.seq_id}")
        if names.get(seq.name) != seq.seq_id:
            bad(f"name {seq.name!r} does not map to sequence {seq.seq_id}")
        if seq.seq_id >= counters["next_seq_id"]:
            bad(f"sequence {seq.seq_id} is beyond next_seq_id {counters['next_seq_id']}")
    if expected != total:
        bad(f"sequences cover {expected} vertices but meta says {total}")
    if len(vrange) != len(seqs):
        bad(f"vertex range index has {len(vrange)} entries for {len(seqs)} sequences")
    if len(names) != len(seqs):
        bad(f"name index has {len(names)} entries for {len(seqs)} sequences")

    # Shards: LMDB lengths agree with the vertex count; files hold at least the committed rows.
    if shard_rows != store.shards.lengths_for(total):
        bad(f"shard lengths in LMDB {shard_rows} do not match {total} vertices")
    for shard, rows in store.shards.lengths_for(total).items():
        path = store.shards.path(shard)
        size = path.stat().st_size if path.exists() else -1
        want = rows * store.shards.row_bytes
        if size < 0:
            bad(f"shard file {path.name} is missing ({rows} committed rows)")
        elif size < want:
            bad(f"shard file {path.name} is truncated: {size} bytes, committed {want}")
        elif size > want:
            report.notes.append(f"{path.name} has {size - want} uncommitted bytes (truncated on "
                                "the next writable open)")
    report.checked["shards"] = len(shard_rows)

    # Edges: endpoints exist, join two different sequences, reverse index mirrors them.
    if counters["n_edges"] != len(edges):
        bad(f"meta says {counters['n_edges']} edges, found {len(edges)}")
    starts = np.array(sorted(s.first_vertex for s in seqs), dtype=np.int64)
    ids_by_start = [s.seq_id for s in sorted(seqs, key=lambda s: s.first_vertex)]

    def seq_of(vid: int) -> int | None:
        if not 0 <= vid < total or not len(starts):
            return None
        return ids_by_start[int(np.searchsorted(starts, vid, side="right")) - 1]

    graph = nx.Graph()
    graph.add_nodes_from(by_id)
    for src, dst in edges:
        a, b = seq_of(src), seq_of(dst)
        if a is None or b is None:
            bad(f"edge {src} -> {dst} has an endpoint outside the map's {total} vertices")
            continue
        if a == b:
            bad(f"edge {src} -> {dst} lies inside sequence {a}")
        graph.add_edge(a, b)
    if sorted((d, s) for s, d in edges) != sorted(rev):
        bad("reverse edge index does not mirror the edges")

    # Union-find: acyclic, matches the membership lists and totals, and partitions the
    # sequences exactly as the edges do.
    roots: dict[int, int] = {}
    for seq_id in by_id:
        if seq_id not in uf:
            bad(f"sequence {seq_id} has no union-find record")
            continue
        node, steps = seq_id, 0
        while uf.get(node, (node,))[0] != node and steps <= len(uf):
            node, steps = uf[node][0], steps + 1
        if steps > len(uf) or node not in uf:
            bad(f"union-find chain of sequence {seq_id} is cyclic or dangling")
            continue
        roots[seq_id] = node
    if set(uf) != set(by_id):
        bad("union-find records do not match the sequences")
    groups: dict[int, set[int]] = {}
    for seq_id, root in roots.items():
        groups.setdefault(root, set()).add(seq_id)
    listed: dict[int, set[int]] = {}
    for root, member in members:
        listed.setdefault(root, set()).add(member)
    if listed != groups:
        bad("component membership lists disagree with union-find")
    for root, group in groups.items():
        if uf[root][1] != len(group):
            bad(f"component {root} size {uf[root][1]} != {len(group)} members")
        want_totals = (len(group), sum(by_id[s].length for s in group))
        if comp.get(root) != want_totals:
            bad(f"component {root} totals {comp.get(root)} != {want_totals}")
    if set(comp) != set(groups):
        bad("component totals exist for non-roots or are missing for roots")
    from_edges = sorted(sorted(c) for c in nx.connected_components(graph))
    if from_edges != sorted(sorted(g) for g in groups.values()):
        bad("union-find components differ from the components recomputed from the edges")
    if counters["n_components"] != len(groups):
        bad(f"meta says {counters['n_components']} components, found {len(groups)}")
    report.checked["components"] = len(groups)

    _check_index(store, total, report, seed)
    for directory in (store.path, store.path / SHARDS_DIR, store.path / INDEX_DIR):
        for entry in directory.iterdir():
            if entry.name.endswith(PARTIAL_SUFFIX):
                bad(f"leftover temp file {entry.relative_to(store.path)}")
    return report


def _check_index(store: MapStore, total: int, report: CheckReport, seed: int) -> None:
    files = index_files(store.path / INDEX_DIR)
    for upto, path in files:
        if upto > total:
            report.violations.append(f"index file {path.name} is ahead of the map ({total} vertices)")
    trusted = [(u, p) for u, p in files if u <= total]
    if not trusted:
        if total:
            report.notes.append("no persisted index; it is rebuilt from the shards on first use")
        return
    upto, path = trusted[-1]
    try:
        index = faiss.read_index(str(path))
    except RuntimeError as exc:
        report.violations.append(f"index file {path.name} is unreadable: {exc}")
        return
    if index.ntotal != upto or index.d != store.config.dim:
        report.violations.append(
            f"index file {path.name} holds {index.ntotal} vectors of dim {index.d}, "
            f"stamped {upto} of dim {store.config.dim}"
        )
        return
    ids = faiss.vector_to_array(index.id_map) if hasattr(index, "id_map") else np.arange(upto)
    if not np.array_equal(np.sort(ids), np.arange(upto)):
        report.violations.append(f"index file {path.name} does not cover vertices 0..{upto - 1}")
        return
    if upto < total:
        report.notes.append(f"index lags the map by {total - upto} vertices (caught up on load)")
    rng = np.random.default_rng(seed)
    sample = np.unique(np.r_[0, upto - 1, rng.integers(0, upto, INDEX_SAMPLE)]) if upto else ()
    for vid in sample:
        stored = index.reconstruct(int(vid))
        try:
            row = store.shards.rows(int(vid), int(vid) + 1, total)[0]
        except StorageIOError as exc:  # a missing/short shard, reported above
            report.notes.append(f"index vector of vertex {vid} not compared: {exc}")
            break
        if not np.array_equal(stored, row):
            report.violations.append(f"index vector of vertex {vid} differs from its shard row")
            break
    report.checked["index_vectors_compared"] = len(sample)
