"""Streaming scans of the whole map from one read snapshot: what an export reads.

An export of a 1M-vertex map must not hold the graph: :class:`MapScan` pins one LMDB read
transaction (so every record it yields is of the same commit, whatever a writer does meanwhile)
and walks the databases with cursors in key order, holding only the sequence records
(O(sequences)) and one drive's positions or one batch of edges at a time:

- :meth:`MapScan.positions` yields each live sequence with its positions (an ``(n, 4)`` array,
  or None), walking ``vertex_data`` forward once;
- :meth:`MapScan.edges` yields every edge with its ``(seq, image)`` endpoints and provenance,
  walking ``edges`` forward once and locating the endpoints of each batch with one
  ``searchsorted`` over the sequences' vertex ranges (no LMDB look-up per endpoint);
- :meth:`MapScan.position` and :meth:`MapScan.has_edge` are single look-ups (O(log n)).

The storage layer hands out records only; formats are the export's business
(:mod:`sprint_map.export`).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import ExitStack, suppress
from typing import TYPE_CHECKING

import lmdb
import numpy as np

from sprint_map.errors import MapCorruptError
from sprint_map.storage.keys import (
    EDGE_KEY,
    EDGE_VAL,
    NO_QUERY,
    Raw,
    decode_vertex,
    read_u64,
    u64,
)
from sprint_map.storage.lmdb_env import LmdbEnv
from sprint_map.storage.records import EdgeInfo, SequenceRecord

if TYPE_CHECKING:
    from sprint_map.storage.store import MapStore

#: Edges decoded and located per batch by :meth:`MapScan.edges`: bounds its memory.
EDGE_BATCH = 65536


class MapScan:
    """The map as of one read transaction, for streaming readers; a context manager.

    Attributes
    ----------
    sequences : list of SequenceRecord
        The live sequences, in vertex order (which is commit order).
    component : dict
        ``seq_id -> component id`` (union-find root).
    vertices : int
        Live vertices (the sum of the sequences' lengths).
    edge_count : int
        Edges (``n_edges``).

    Notes
    -----
    Opening is O(sequences) reads and memory; the scans stream. Holding it pins the LMDB pages
    of its snapshot, like any reader.
    """

    def __init__(self, store: MapStore) -> None:
        self.store = store
        self._stack = ExitStack()
        self.txn: lmdb.Transaction = self._stack.enter_context(store.env.read())
        try:
            env = store.env
            self.sequences = sorted(
                (SequenceRecord.decode(v) for _, v in self.txn.cursor(db=env.db("sequences"))),
                key=lambda s: s.first_vertex)
            self.component = {}
            for root, _, _ in store.uf.components(self.txn):
                for member in store.uf.members(self.txn, root):
                    self.component[member] = root
            self.vertices = sum(s.length for s in self.sequences)
            self.edge_count = store.counter("n_edges", self.txn)
            self._first = np.array([s.first_vertex for s in self.sequences], dtype=np.int64)
            self._last = np.array([s.last_vertex for s in self.sequences], dtype=np.int64)
            self._ids = np.array([s.seq_id for s in self.sequences], dtype=np.int64)
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        """Release the read transaction. Idempotent."""
        with suppress(lmdb.Error):
            self._stack.close()

    def __enter__(self) -> MapScan:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def positions(self) -> Iterator[tuple[SequenceRecord, np.ndarray | None]]:
        """Each live sequence in vertex order with its ``(length, 4)`` positions ``x, y,
        heading_deg, timestamp`` (NaN where unknown), or None if it has none.

        Notes
        -----
        One forward walk of ``vertex_data``: O(vertices with positions) reads, memory of one
        sequence's positions.
        """
        with LmdbEnv.translated():
            yield from self._positions()

    def _positions(self) -> Iterator[tuple[SequenceRecord, np.ndarray | None]]:
        cursor = self.txn.cursor(db=self.store.env.db("vertex_data"))
        for seq in self.sequences:
            if not cursor.set_range(u64(seq.first_vertex)) or read_u64(
                    cursor.key()) > seq.last_vertex:
                yield seq, None
                continue
            out = np.full((seq.length, 5), np.nan)
            for key, value in cursor:
                vid = read_u64(key)
                if vid > seq.last_vertex:
                    break
                out[vid - seq.first_vertex] = decode_vertex(value)
            yield seq, out

    def locate(self, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(seq ids, image ids)`` of vertex ids of live sequences. O(n log sequences).

        Raises
        ------
        MapCorruptError
            A vertex in no live sequence (an edge to a removed range or past the map).
        """
        at = np.searchsorted(self._first, vertices, side="right") - 1
        safe = np.maximum(at, 0)
        inside = (at >= 0) & (vertices <= self._last[safe]) if len(self._first) else (
            np.zeros(len(vertices), dtype=bool))
        if not inside.all():
            bad = int(vertices[np.flatnonzero(~inside)[0]])
            raise MapCorruptError(f"edge endpoint {bad} is in no live sequence")
        return self._ids[safe], vertices - self._first[safe]

    def edges(self) -> Iterator[tuple[int, int, EdgeInfo]]:
        """Every edge as ``(src vertex, dst vertex, EdgeInfo)``, in (src, dst) order.

        Notes
        -----
        One forward walk of ``edges``: O(E) reads plus O(E log sequences) to locate the
        endpoints, in batches of :data:`EDGE_BATCH` (the memory bound).
        """
        with LmdbEnv.translated():
            yield from self._edges()

    def _edges(self) -> Iterator[tuple[int, int, EdgeInfo]]:
        keys: list[Raw] = []
        values: list[Raw] = []
        for key, value in self.txn.cursor(db=self.store.env.db("edges")):
            keys.append(key)
            values.append(value)
            if len(keys) == EDGE_BATCH:
                yield from self._located(keys, values)
                keys, values = [], []
        if keys:
            yield from self._located(keys, values)

    def _located(self, keys: list[Raw], values: list[Raw]
                 ) -> Iterator[tuple[int, int, EdgeInfo]]:
        for key in keys:
            if len(key) != EDGE_KEY.size:
                EDGE_KEY.unpack(key)  # raises MapCorruptError
        ends = np.frombuffer(b"".join(keys), dtype=">u8").astype(np.int64).reshape(-1, 2)
        src_seq, src_img = self.locate(ends[:, 0])
        dst_seq, dst_img = self.locate(ends[:, 1])
        rows = zip(ends.tolist(), src_seq.tolist(), src_img.tolist(), dst_seq.tolist(),
                   dst_img.tolist(), values, strict=True)
        for (src, dst), s_seq, s_img, d_seq, d_img, value in rows:
            weight, query, frame, when = EDGE_VAL.unpack(value)
            yield src, dst, EdgeInfo(s_seq, s_img, d_seq, d_img, weight,
                                     None if query == NO_QUERY else query,
                                     None if frame == NO_QUERY else frame, when)

    def position(self, vertex: int) -> tuple[float, float, float, float, float] | None:
        """``x, y, heading_deg, timestamp, sigma_m`` of one vertex, or None. O(log n)."""
        with LmdbEnv.translated():
            raw = self.txn.get(u64(vertex), db=self.store.env.db("vertex_data"))
        return None if raw is None else decode_vertex(raw)

    def has_position(self, first: int, last: int) -> bool:
        """Whether any vertex ``first..last`` has a position. O(log n)."""
        with LmdbEnv.translated():
            cursor = self.txn.cursor(db=self.store.env.db("vertex_data"))
            return bool(cursor.set_range(u64(first))) and read_u64(cursor.key()) <= last

    def has_edge(self, src: int, dst: int) -> bool:
        """Whether the edge ``src -> dst`` (vertex ids) exists. O(log E)."""
        with LmdbEnv.translated():
            return self.txn.get(EDGE_KEY.pack(src, dst), db=self.store.env.db("edges")) is not None


__all__ = ["EDGE_BATCH", "MapScan"]
