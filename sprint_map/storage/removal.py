"""Removing sequences (forgetting stale drives) and searching around what was removed.

:func:`remove_sequences` retires sequences in **one** LMDB write transaction: their records,
names, vertex ranges, positions and thumbnails go, every edge to or from them goes (both
directions and the reverse index), and the components they were in are rebuilt from the edges that remain. A
union-find cannot split a set, so the affected components (only those) are recomputed: their
records are deleted and the remaining members regrouped by the edges among them. The removed
vertex ranges are recorded in the ``removed`` database (key: last vertex, value: first vertex
and the sequence id), so that live sequences plus removed ranges still tile the vertex ids
``0..next_vertex_id-1`` and vertex ids stay stable until ``compact`` renumbers them.

The descriptors of removed vertices stay in the shards and the index until ``compact``
reclaims them; :func:`search_live` filters them out of every search.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable, Iterable
from typing import Any, Protocol

import lmdb
import numpy as np

from sprint_map.errors import MapCorruptError
from sprint_map.storage.components import MEMBER_KEY, ComponentStore
from sprint_map.storage.drive_stats import delete_drive_stats
from sprint_map.storage.keys import COMP_VAL, EDGE_KEY, REMOVED_VAL, UF_VAL, read_u64, u32, u64
from sprint_map.storage.lmdb_env import LmdbEnv
from sprint_map.storage.records import EdgeTable, RemoveResult, SequenceRecord
from sprint_map.storage.sightings import delete_sightings
from sprint_map.storage.thumbnails import delete_thumbnails
from sprint_map.testing.crash import crash_point
from sprint_map.util.arrays import Descriptors, SearchResult
from sprint_map.util.union_find import UnionFind


class RecordStore(Protocol):
    """The LMDB records of an open map that removal and unmerging rewrite (``MapStore`` is
    one): its environment, union-find, counters and sequence records."""

    @property
    def env(self) -> LmdbEnv: ...

    @property
    def uf(self) -> ComponentStore: ...

    def counter(self, name: str, txn: lmdb.Transaction | None = None) -> int: ...

    def sequence(self, seq_id: int, txn: lmdb.Transaction | None = None) -> SequenceRecord: ...

    def removed_vertices(self, txn: lmdb.Transaction | None = None) -> int: ...

    def edge_table_from(self, ranges: Iterable[tuple[int, int]], txn: lmdb.Transaction
                        ) -> EdgeTable: ...


class RemovedRanges:
    """Sorted removed vertex ranges ``[first, last]`` with a vectorised membership test."""

    def __init__(self, first: np.ndarray, last: np.ndarray, seq_ids: np.ndarray) -> None:
        self.first = first
        self.last = last
        self.seq_ids = seq_ids

    @classmethod
    def read(cls, env: LmdbEnv, txn: lmdb.Transaction) -> RemovedRanges:
        """Every removed range recorded in ``txn``. O(removed sequences)."""
        rows: list[tuple[int, int, int]] = []
        if env.has_db("removed"):
            for key, value in txn.cursor(db=env.db("removed")):
                first, seq = REMOVED_VAL.unpack(value)
                rows.append((int(first), read_u64(key), int(seq)))
        arr = np.array(rows, dtype=np.int64).reshape(-1, 3)
        return cls(arr[:, 0].copy(), arr[:, 1].copy(), arr[:, 2].copy())

    @property
    def count(self) -> int:
        """Number of removed ranges."""
        return len(self.first)

    @property
    def vertices(self) -> int:
        return int((self.last - self.first + 1).sum())

    def contains(self, vertex_ids: np.ndarray) -> np.ndarray:
        """Boolean mask: which ids lie in a removed range. O(n log ranges)."""
        ids = np.asarray(vertex_ids, dtype=np.int64)
        at = np.searchsorted(self.last, ids, side="left")
        inside = at < len(self.last)
        out = np.zeros(ids.shape, dtype=bool)
        out[inside] = self.first[at[inside]] <= ids[inside]
        return out

    def search_live(self, search: Callable[[Descriptors, int], SearchResult],
                    queries: Descriptors, k: int, indexed: int) -> SearchResult:
        """k nearest vertices outside these ranges, by ``search`` over ``indexed`` vectors (any
        search over the map's vertex ids, e.g. the fleet's sharded one): :func:`search_live`."""
        return search_live(search, queries, k, self, indexed)


def search_live(search: Callable[[Descriptors, int], SearchResult],
                queries: Descriptors, k: int, removed: RemovedRanges, indexed: int
                ) -> SearchResult:
    """k nearest *live* vertices: ``search`` over-fetches and hits in removed ranges are dropped.

    Each query is first asked for ``k`` plus as many candidates again (at least 16); the
    queries that still have fewer than ``k`` live hits while the index returned a full list are
    asked again with four times as many, until the index (``indexed`` vectors) is exhausted.
    Rows are padded like FAISS pads them (id -1, distance ``float32`` max).

    Notes
    -----
    One search of ``2k + 16`` candidates when removed vertices are rare among the neighbours;
    O(log(indexed / k)) rounds in the worst case (every neighbour removed).
    """
    n = len(queries)
    out_d = np.full((n, k), np.finfo(np.float32).max, dtype=np.float32)
    out_i = np.full((n, k), -1, dtype=np.int64)
    todo = np.arange(n)
    fetch = min(max(2 * k, k + 16), max(indexed, 1))
    while len(todo):
        dists, ids = search(np.ascontiguousarray(queries[todo]), fetch)
        live = (ids >= 0) & ~removed.contains(ids)
        got = live.sum(axis=1)
        exhausted = (ids[:, -1] < 0) | (fetch >= indexed)
        finished = (got >= k) | exhausted
        for row in np.flatnonzero(finished):
            keep = np.flatnonzero(live[row])[:k]
            out_d[todo[row], : len(keep)] = dists[row, keep]
            out_i[todo[row], : len(keep)] = ids[row, keep]
        todo = todo[~finished]
        fetch = min(fetch * 4, indexed)
    return out_d, out_i


def edge_keys(txn: lmdb.Transaction, db: Any, first: int, last: int) -> list[tuple[int, int]]:
    """Keys ``(a, b)`` of ``db`` (edges or edges_rev) with ``first <= a <= last``.

    O(log E + keys returned): one seek, then a range scan.
    """
    out = []
    cursor = txn.cursor(db=db)
    if cursor.set_range(EDGE_KEY.pack(first, 0)):
        for key in cursor.iternext(keys=True, values=False):
            a, b = EDGE_KEY.unpack(key)
            if a > last:
                break
            out.append((a, b))
    return out


def remove_sequences(store: RecordStore, seq_ids: Iterable[int]) -> RemoveResult:
    """Retire the sequences ``seq_ids`` and everything attached to them, atomically.

    Raises
    ------
    UnknownSequenceError
        If a sequence does not exist (nothing is changed).

    Notes
    -----
    One write transaction. O(L + E_r + S_c + E_c) LMDB operations: L positions (and
    thumbnails) of the removed sequences, E_r edges touching them, and the S_c sequences and
    E_c edges of the affected components (their edges are read once to regroup them). Nothing
    else of the map is read.
    """
    wanted = sorted(dict.fromkeys(int(s) for s in seq_ids))
    env = store.env
    db = env.db

    def body(txn: lmdb.Transaction) -> RemoveResult:
        records = [store.sequence(s, txn) for s in wanted]  # UnknownSequenceError first
        gone = set(wanted)
        roots = sorted({store.uf.find(txn, s) for s in wanted})
        members = {root: store.uf.members(txn, root) for root in roots}
        # 1. every edge from or to a removed sequence, with its reverse entry
        doomed: set[tuple[int, int]] = set()
        for rec in records:
            doomed.update(edge_keys(txn, db("edges"), rec.first_vertex, rec.last_vertex))
            doomed.update((src, dst) for dst, src in
                          edge_keys(txn, db("edges_rev"), rec.first_vertex, rec.last_vertex))
        edges_removed = 0
        for src, dst in sorted(doomed):
            edges_removed += bool(txn.delete(EDGE_KEY.pack(src, dst), db=db("edges")))
            txn.delete(EDGE_KEY.pack(dst, src), db=db("edges_rev"))
        # 2. the sequences: record, name, vertex range, positions, thumbnails, sightings -> a
        # removed range
        for rec in records:
            delete_thumbnails(txn, env, rec.seq_id)
            delete_sightings(txn, env, rec.seq_id)
            delete_drive_stats(txn, env, rec.seq_id)
            txn.delete(u32(rec.seq_id), db=db("sequences"))
            txn.delete(rec.name.encode(), db=db("seq_names"))
            txn.delete(u64(rec.last_vertex), db=db("vrange"))
            cursor = txn.cursor(db=db("vertex_data"))
            at = cursor.set_range(u64(rec.first_vertex))
            while at and read_u64(cursor.key()) <= rec.last_vertex:
                cursor.delete()  # moves to the next record (an empty key past the last)
                at = bool(cursor.key())
            txn.put(u64(rec.last_vertex), REMOVED_VAL.pack(rec.first_vertex, rec.seq_id),
                    db=db("removed"))
        # 3. the affected components, regrouped by the edges that remain
        after = rebuild_components(store, txn, members, gone)
        meta = db("meta")
        counters = {name: store.counter(name, txn) for name in
                    ("n_sequences", "n_edges", "n_components")}
        txn.put(b"n_sequences", u64(counters["n_sequences"] - len(records)), db=meta)
        txn.put(b"n_edges", u64(counters["n_edges"] - edges_removed), db=meta)
        txn.put(b"n_components", u64(counters["n_components"] - len(roots) + len(after)),
                db=meta)
        txn.put(b"removed_vertices", u64(store.removed_vertices(txn)
                                         + sum(r.length for r in records)), db=meta)
        crash_point("remove.before_commit")
        return RemoveResult(records, edges_removed, roots, sorted(after))

    result = env.write(body)
    crash_point("remove.committed")
    return result


def rebuild_components(store: RecordStore, txn: lmdb.Transaction, members: dict[int, list[int]],
                       gone: set[int] | frozenset[int] = frozenset()) -> list[int]:
    """Rebuild the components ``members`` (root -> its member sequences, read before any
    change) from the edges that remain in ``txn``; return the roots of the parts, ascending.

    A union-find cannot split a set, so each component is dissolved (its ``uf``, ``members``
    and ``comp`` records deleted) and its members but ``gone`` (sequences being removed)
    regrouped by the edges among them (:func:`regroup`). The part holding the old root keeps
    the old id, the other parts take their smallest sequence id. Used by ``remove`` (``gone``:
    the removed sequences) and ``unmerge`` (nothing gone, edges revoked). The caller updates
    ``n_components`` (``- len(members) + len(result)``).

    Notes
    -----
    O(S_c log S_c + E_c) LMDB operations for the S_c sequences and E_c edges of the given
    components; nothing else of the map is read.
    """
    env = store.env
    after: list[int] = []
    for root, seqs in members.items():
        remaining = [store.sequence(m, txn) for m in seqs if m not in gone]
        for member in seqs:
            txn.delete(u32(member), db=env.db("uf"))
            txn.delete(MEMBER_KEY.pack(root, member), db=env.db("members"))
        txn.delete(u32(root), db=env.db("comp"))
        for group in regroup(store, txn, remaining):
            after.append(write_component(txn, env, group, prefer=root))
    return sorted(after)


def regroup(store: RecordStore, txn: lmdb.Transaction, seqs: list[SequenceRecord]
            ) -> list[list[SequenceRecord]]:
    """Connected components of ``seqs`` (one former component) by the edges among them.

    Every edge leaving one of them ends in another (they were one component and the edges to
    removed sequences are gone), so reading their out-edges is enough. O(S log S + E) with an
    in-memory union-find.
    """
    ordered = sorted(seqs, key=lambda s: s.first_vertex)
    starts = [s.first_vertex for s in ordered]
    sets = UnionFind(len(ordered))
    for i, seq in enumerate(ordered):
        for _, dst in edge_keys(txn, store.env.db("edges"), seq.first_vertex, seq.last_vertex):
            j = bisect.bisect_right(starts, dst) - 1
            if j < 0 or dst > ordered[j].last_vertex:
                raise MapCorruptError(f"edge {seq.first_vertex}.. -> {dst} leaves the component "
                                      f"of sequence {seq.seq_id}")
            sets.union(i, j)
    return [[ordered[i] for i in members] for members in sets.groups()]


def write_component(txn: lmdb.Transaction, env: LmdbEnv, group: list[SequenceRecord],
                    prefer: int) -> int:
    """Write union-find rows, member keys and totals of one component; return its root.

    The root is ``prefer`` (the former component's id) if it is a member, so the part that
    keeps the old root keeps the old id; else the smallest sequence id.
    """
    ids = sorted(s.seq_id for s in group)
    root = prefer if prefer in ids else ids[0]
    for seq in ids:
        txn.put(u32(seq), UF_VAL.pack(root, len(ids) if seq == root else 1), db=env.db("uf"))
        txn.put(MEMBER_KEY.pack(root, seq), b"", db=env.db("members"))
    txn.put(u32(root), COMP_VAL.pack(len(ids), sum(s.length for s in group)),
            db=env.db("comp"))
    return root


__all__ = ["RecordStore", "RemovedRanges", "edge_keys", "rebuild_components", "regroup",
           "remove_sequences", "search_live", "write_component"]
