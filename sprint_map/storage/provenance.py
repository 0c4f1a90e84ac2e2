"""Edges with their provenance, and undoing one drive's merge (``unmerge``).

Every edge records the drive whose commit wrote it: the ``query seq`` field of its value
(:data:`~sprint_map.storage.keys.EDGE_VAL`, there since schema 1), with the query frame, the
probability and the commit time. A drive's edges usually touch the drive itself (its frames
matched to the map), but :meth:`MapStore.add_sequence` also accepts edges between two earlier
sequences; those carry the adding drive's id too. An edge written again by a later commit keeps
the newest provenance (only the newest is stored).

:func:`unmerge_sequence` revokes every edge one drive added (both directions are separate edges
and each goes with its reverse entry) in **one** LMDB write transaction, and rebuilds the
components those edges held together, and only those
(:func:`~sprint_map.storage.removal.rebuild_components`, shared with ``remove``). The drive
stays in the map; edges that later drives added to it stay too.

Finding a drive's edges needs no index: vertex ids are assigned in commit order (and
``compact`` keeps that order), so every edge a drive ``S`` added has its source vertex at or
below the last vertex of ``S``. One range scan of ``edges`` up to there, comparing the
provenance bytes of each value, finds them all: O(E_S) for the E_S edges whose source vertex is
not past ``S`` (all edges for the newest drive, few for an old one).
"""

from __future__ import annotations

import struct

import lmdb

from sprint_map.errors import MapCorruptError
from sprint_map.storage.keys import EDGE_KEY, EDGE_VAL, read_u32, u32, u64
from sprint_map.storage.records import EdgeInfo, EdgeRecord, EdgeTable, UnmergeResult
from sprint_map.storage.removal import RecordStore, edge_keys, rebuild_components
from sprint_map.testing.crash import crash_point

#: Byte offset of the adding sequence's id (``>I``) inside an edge value, after the ``>d``
#: weight: a scan compares these 4 bytes without decoding the value.
ADDED_BY_AT = struct.calcsize(EDGE_VAL.format[:2])


class _Locator:
    """``vertex -> (seq_id, image_id)`` in one transaction: one ``vrange`` seek per vertex,
    each sequence record decoded once."""

    def __init__(self, store: RecordStore, txn: lmdb.Transaction) -> None:
        self._store = store
        self._txn = txn
        self._cursor = txn.cursor(db=store.env.db("vrange"))
        self._first: dict[int, int] = {}

    def __call__(self, vertex: int) -> tuple[int, int]:
        if not self._cursor.set_range(u64(vertex)):
            raise MapCorruptError(f"edge endpoint {vertex} lies past the last live sequence")
        seq = read_u32(self._cursor.value())
        first = self._first.get(seq)
        if first is None:
            first = self._first[seq] = self._store.sequence(seq, self._txn).first_vertex
        if vertex < first:
            raise MapCorruptError(f"edge endpoint {vertex} lies in a removed vertex range")
        return seq, vertex - first


def edges_added_by(store: RecordStore, txn: lmdb.Transaction, seq_id: int) -> list[EdgeRecord]:
    """Every edge whose provenance is sequence ``seq_id`` (which must be live), by key.

    Raises
    ------
    UnknownSequenceError
        No live sequence ``seq_id``.

    Notes
    -----
    One range scan of ``edges`` from the first key to the last vertex of ``seq_id``: O(E_S)
    reads, E_S the edges whose source vertex is not past that sequence (see the module notes).
    """
    last = store.sequence(seq_id, txn).last_vertex
    want = u32(seq_id)
    out = []
    for key, value in txn.cursor(db=store.env.db("edges")):
        if EDGE_KEY.unpack(key)[0] > last:
            break
        if value[ADDED_BY_AT:ADDED_BY_AT + 4] == want:
            out.append(EdgeRecord.decode(key, value))
    return out


def edges_touching(store: RecordStore, txn: lmdb.Transaction, seq_id: int) -> list[EdgeRecord]:
    """Every edge from or to sequence ``seq_id``, by key.

    Notes
    -----
    Two range scans (``edges`` from its vertex range, ``edges_rev`` into it) and one get per
    incoming edge: O(log E + edges returned).
    """
    rec = store.sequence(seq_id, txn)
    edges = store.env.db("edges")
    keys = edge_keys(txn, edges, rec.first_vertex, rec.last_vertex)
    keys += [(src, dst) for dst, src in
             edge_keys(txn, store.env.db("edges_rev"), rec.first_vertex, rec.last_vertex)]
    out = []
    for src, dst in sorted(set(keys)):
        key = EDGE_KEY.pack(src, dst)
        value = txn.get(key, db=edges)
        if value is None:
            raise MapCorruptError(f"reverse edge index names a missing edge {src} -> {dst}")
        out.append(EdgeRecord.decode(key, value))
    return out


def edge_table(store: RecordStore) -> EdgeTable:
    """Every edge of the map as arrays (one read snapshot), for summaries of large maps.

    Notes
    -----
    O(E): :meth:`StoreReads.edge_table_from <sprint_map.storage.store_reads.StoreReads.edge_table_from>`
    over every source vertex, one cursor pass decoded with numpy.
    """
    with store.env.read() as txn:
        return store.edge_table_from([(0, 2 ** 64 - 1)], txn)


def list_edges(store: RecordStore, seq: int | None = None, added_by: int | None = None
               ) -> list[EdgeInfo]:
    """Edges with ``(seq, image)`` endpoints and provenance, ordered by (src, dst) vertex.

    Parameters
    ----------
    seq : int, optional
        Only edges touching sequence ``seq`` (either end).
    added_by : int, optional
        Only edges that sequence ``added_by`` added: exactly what ``unmerge`` of it revokes.

    Raises
    ------
    UnknownSequenceError
        ``seq`` or ``added_by`` is not a live sequence.

    Notes
    -----
    One read snapshot. O(log E + edges touching ``seq``) with ``seq``; O(E_S) with only
    ``added_by`` (:func:`edges_added_by`); O(E) for every edge. Plus O(log n) per endpoint.
    """
    with store.env.read() as txn:
        if added_by is not None:
            store.sequence(added_by, txn)
        if seq is not None:
            records = edges_touching(store, txn, seq)
            if added_by is not None:
                records = [e for e in records if e.query_seq == added_by]
        elif added_by is not None:
            records = edges_added_by(store, txn, added_by)
        else:
            records = [EdgeRecord.decode(k, v) for k, v in
                       txn.cursor(db=store.env.db("edges"))]
        locate = _Locator(store, txn)
        out = []
        for e in records:
            (src_seq, src_image), (dst_seq, dst_image) = locate(e.src), locate(e.dst)
            out.append(EdgeInfo(src_seq, src_image, dst_seq, dst_image, e.weight, e.query_seq,
                                e.frame, e.time))
        return out


def unmerge_sequence(store: RecordStore, seq_id: int) -> UnmergeResult:
    """Revoke every edge sequence ``seq_id`` added when it was merged, atomically.

    Both directions of a match are separate edges with the same provenance: both go, each with
    its reverse entry. The components those edges were in (only those) are rebuilt from the
    edges that remain, so they split where nothing else joins them; the part holding a former
    root keeps its id. The sequence itself, its descriptors and positions, and the edges later
    drives added to it stay. A drive that added no edge (or was unmerged already) is a no-op
    reporting 0.

    Raises
    ------
    UnknownSequenceError
        No live sequence ``seq_id`` (nothing is changed).

    Notes
    -----
    One write transaction (crash points ``unmerge.before_commit``, ``unmerge.committed``).
    O(E_S) reads to find the edges (:func:`edges_added_by`), O(log n) per revoked edge to
    locate it, and O(S_c log S_c + E_c) for the S_c sequences and E_c edges of the affected
    components; nothing else of the map is read.
    """
    env = store.env
    db = env.db

    def body(txn: lmdb.Transaction) -> UnmergeResult:
        revoked = edges_added_by(store, txn, seq_id)  # UnknownSequenceError first
        locate = _Locator(store, txn)
        touched = {locate(v)[0] for e in revoked for v in (e.src, e.dst)}
        roots = sorted({store.uf.find(txn, seq) for seq in touched})
        members = {root: store.uf.members(txn, root) for root in roots}
        for e in revoked:
            txn.delete(EDGE_KEY.pack(e.src, e.dst), db=db("edges"))
            txn.delete(EDGE_KEY.pack(e.dst, e.src), db=db("edges_rev"))
        after = rebuild_components(store, txn, members)
        if revoked:
            meta = db("meta")
            n_edges, n_components = (store.counter(name, txn)
                                     for name in ("n_edges", "n_components"))
            txn.put(b"n_edges", u64(n_edges - len(revoked)), db=meta)
            txn.put(b"n_components", u64(n_components - len(roots) + len(after)), db=meta)
        crash_point("unmerge.before_commit")
        return UnmergeResult(seq_id, len(revoked), after)

    result = env.write(body)
    crash_point("unmerge.committed")
    return result


__all__ = ["ADDED_BY_AT", "edge_table", "edges_added_by", "edges_touching",
           "list_edges", "unmerge_sequence"]
