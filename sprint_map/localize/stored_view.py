"""The HMM's view of a persistent map: components as compact arrays, loaded on demand.

:class:`StoredMapView` implements the :class:`sprint_map.hmm.graph.GraphSource` protocol over
LMDB, so the HMM (which knows nothing of storage) can ask for the component of a retrieved
vertex and for a component's sequences and edges. Nothing else of the map is touched.

It is also the localiser's one view of the map: :meth:`StoredMapView.pinned` holds one
:class:`~sprint_map.storage.snapshot.MapSnapshot` for a whole ``localize`` (or one ``step``), and
the search, the component look-ups and loads and ``locate`` all read that snapshot, so a writer
committing meanwhile (a merge, a ``remove``) is never half seen.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import lmdb
import numpy as np

from sprint_map.errors import MapCorruptError
from sprint_map.hmm.graph import ComponentGraph
from sprint_map.storage.keys import read_u32, read_u64, u64
from sprint_map.storage.records import SequenceRecord
from sprint_map.storage.snapshot import MapSnapshot
from sprint_map.storage.store import MapStore
from sprint_map.util.arrays import DescriptorsLike, SearchResult

__all__ = ["StoredMapView"]


class StoredMapView:
    """GraphSource over a :class:`MapStore`.

    Notes
    -----
    ``components_of`` costs one LMDB cursor seek per vertex and one union-find walk and one
    sequence read per distinct sequence: O(k log n_sequences) per frame for k hits. Inside
    :meth:`pinned` the sequences already read at that map version answer from memory
    (:class:`KnownSequences`), so a drive pays the LMDB reads once per sequence it meets. Removed
    sequences are invisible: their records, edges and component memberships are gone, and the
    store's search never returns their vertices. ``load_component`` costs
    O(S log n + E_c) for a component of S sequences and E_c edges.

    Outside :meth:`pinned` every call reads its own snapshot (fine for a map nobody writes);
    inside it, every call reads the pinned one.
    """

    def __init__(self, store: MapStore) -> None:
        self.store = store
        self._snapshot: MapSnapshot | None = None
        #: Version (:attr:`MapSnapshot.version`) of the map the caller's state reflects.
        self._seen: int | None = None
        #: The sequences ``components_of`` has read, for the version they were read at.
        self._known: KnownSequences | None = None

    # --- the pinned snapshot ----------------------------------------------------------------
    @contextmanager
    def pinned(self) -> Iterator[bool]:
        """Pin one snapshot of the map for the calls made in the ``with`` block.

        Yields whether the map changed since the previous pin (never on the first): the
        caller's state built from earlier snapshots (its component cache, the belief's
        components) is then stale and must be re-read (``SprintFilter.invalidate``).
        Re-entrant: a nested pin keeps the outer snapshot (and yields False).
        """
        if self._snapshot is not None:
            yield False
            return
        snap = MapSnapshot(self.store)
        changed = self._seen is not None and snap.version != self._seen
        self._seen = snap.version
        self._snapshot = snap
        try:
            yield changed
        finally:
            self._snapshot = None
            snap.close()

    def mark_current(self) -> None:
        """The caller has brought its state up to date with the map as of now (or with the
        pinned snapshot): the next pin reports changes after that only."""
        if self._snapshot is not None:
            self._seen = self._snapshot.version
        else:
            self._seen = None

    @property
    def vertices(self) -> int:
        """Vertex ids of the map (pinned snapshot, else now): ``next_vertex_id``."""
        if self._snapshot is not None:
            return self._snapshot.vertices
        return self.store.counter("next_vertex_id")

    def visible(self, vertex_ids: np.ndarray) -> np.ndarray:
        """Which of ``vertex_ids`` the map holds (pinned snapshot, else now): ids below its
        vertex count and outside its removed ranges (``-1`` pads: False). O(n log ranges)."""
        ids = np.asarray(vertex_ids, dtype=np.int64)
        snap = self._snapshot
        if snap is None:
            with MapSnapshot(self.store) as now:
                live: np.ndarray = (ids >= 0) & (ids < now.vertices) & ~now.removed.contains(ids)
                return live
        held: np.ndarray = (ids >= 0) & (ids < snap.vertices) & ~snap.removed.contains(ids)
        return held

    @contextmanager
    def _txn(self) -> Iterator[lmdb.Transaction]:
        if self._snapshot is not None:
            with self.store.env.translated():
                yield self._snapshot.txn
        else:
            with self.store.env.read() as txn:
                yield txn

    def search(self, queries: DescriptorsLike, k: int) -> SearchResult:
        """k nearest live vertices of each query (pinned snapshot, else now), -1 padded."""
        if self._snapshot is not None:
            return self._snapshot.search(queries, k)
        return self.store.search(queries, k)

    def locate(self, vertex_ids: Any) -> list[tuple[int, int]]:
        """``(seq_id, image_id)`` of each vertex id (pinned snapshot, else now)."""
        with self._txn() as txn:
            return self.store.locate(vertex_ids, txn)

    # --- GraphSource ------------------------------------------------------------------------
    def components_of(self, vertex_ids: np.ndarray) -> np.ndarray:
        """Component id (union-find root sequence) of each global vertex id."""
        ids = np.asarray(vertex_ids, dtype=np.int64).ravel()
        snap = self._snapshot
        if snap is None:
            return self._components_read(ids, None)
        known = self._known
        if known is None or known.version != snap.version:
            known = self._known = KnownSequences(snap.version)
        out, missing = known.lookup(ids)
        if missing.any():
            out[missing] = self._components_read(ids[missing], known)
        return out

    def sequence_first(self, vertex_ids: np.ndarray) -> np.ndarray:
        """The first vertex id of each global vertex id's sequence (the HMM's drive rival,
        :func:`~sprint_map.hmm.observation.sequence_first_of`); the same reads as
        :meth:`components_of`, from memory for the sequences known at the pinned version."""
        ids = np.asarray(vertex_ids, dtype=np.int64).ravel()
        snap = self._snapshot
        if snap is None:
            firsts = np.empty(len(ids), dtype=np.int64)
            self._components_read(ids, None, firsts)
            return firsts
        self.components_of(ids)  # every range now known at this version
        assert self._known is not None
        return self._known.firsts(ids)

    def _components_read(self, ids: np.ndarray, known: KnownSequences | None,
                         firsts: np.ndarray | None = None) -> np.ndarray:
        """:meth:`components_of` from LMDB (each sequence met recorded in ``known``; each
        vertex's sequence's first vertex written to ``firsts`` if given)."""
        store = self.store
        out = np.empty(len(ids), dtype=np.int64)
        with self._txn() as txn:
            cursor = txn.cursor(db=store.env.db("vrange"))
            roots: dict[int, tuple[int, int]] = {}  # seq -> (root, first vertex)
            for i, vid in enumerate(ids.tolist()):
                if vid < 0 or not cursor.set_range(u64(vid)):
                    raise ValueError(f"vertex {vid} is not in the map")
                seq = read_u32(cursor.value())
                found = roots.get(seq)
                if found is None:
                    found = roots[seq] = (store.uf.find(txn, seq),
                                          store.sequence(seq, txn).first_vertex)
                    if known is not None:
                        known.learn(found[1], read_u64(cursor.key()), found[0])
                if vid < found[1]:  # the floor seek passed a removed range: never a hit
                    raise ValueError(f"vertex {vid} belonged to a removed sequence")
                out[i] = found[0]
                if firsts is not None:
                    firsts[i] = found[1]
        return out

    def load_component(self, component_id: int) -> ComponentGraph:
        """The sequences and inter-sequence edges of one component, as compact arrays."""
        store = self.store
        with self._txn() as txn:
            seqs = store.component_sequences(component_id, txn)
            edges = store.edge_table_from(((s.first_vertex, s.last_vertex) for s in seqs), txn)
        _edges_inside(component_id, seqs, edges.src, edges.dst)
        return ComponentGraph(
            component_id=component_id,
            seq_ids=np.array([s.seq_id for s in seqs], dtype=np.int64),
            seq_first=np.array([s.first_vertex for s in seqs], dtype=np.int64),
            seq_len=np.array([s.length for s in seqs], dtype=np.int64),
            edge_src=edges.src,
            edge_dst=edges.dst,
            edge_weight=edges.prob,
        )


def _edges_inside(component_id: int, seqs: list[SequenceRecord], src: np.ndarray,
                  dst: np.ndarray) -> None:
    """Refuse a component whose stored edges leave it (a corrupt edge record: MapCorruptError,
    never a graph built on it). O((E + S) log S)."""
    if not src.size or not seqs:
        return
    ordered = sorted(seqs, key=lambda s: s.first_vertex)
    firsts = np.array([s.first_vertex for s in ordered], dtype=np.int64)
    lasts = np.array([s.last_vertex for s in ordered], dtype=np.int64)
    top = int(lasts.max())
    ends = np.minimum(np.stack([src, dst]), top + 1)
    at = np.maximum(np.searchsorted(firsts, ends, side="right") - 1, 0)
    outside = (ends < firsts[at]) | (ends > lasts[at])
    if outside.any():
        bad = int(np.flatnonzero(outside.any(axis=0))[0])
        raise MapCorruptError(f"edge {src[bad]} -> {dst[bad]} of component {component_id} "
                              "leaves it: the map's edge records are corrupt (see "
                              "`sprint-map check`)")


class KnownSequences:
    """The vertex ranges and components of the sequences read at one map version.

    A sequence's vertices are one range ``first .. last`` and ranges never overlap, so a vertex
    inside a known range belongs to that sequence exactly as the LMDB floor seek would say; at
    another version nothing known holds (a merge changes roots, a removal ranges).

    Notes
    -----
    :meth:`lookup` is O(n log s) for n vertices and s known sequences, a few numpy calls;
    :meth:`learn` is O(1) and the next lookup re-sorts, O(s log s).
    """

    def __init__(self, version: int) -> None:
        self.version = version
        self._rows: list[tuple[int, int, int]] = []  # (first, last, root)
        self._arrays: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def learn(self, first: int, last: int, root: int) -> None:
        """Record that vertices ``first .. last`` are one sequence of component ``root``."""
        self._rows.append((first, last, root))
        self._arrays = None

    def lookup(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Component of each of ``ids`` (int64) where a known range holds it, and the mask of
        those no known range holds (their entries are undefined)."""
        if self._arrays is None:
            rows = np.array(sorted(self._rows), dtype=np.int64).reshape(-1, 3)
            self._arrays = (rows[:, 0].copy(), rows[:, 1].copy(), rows[:, 2].copy())
        firsts, lasts, roots = self._arrays
        if not firsts.size:
            return np.empty(len(ids), dtype=np.int64), np.ones(len(ids), dtype=bool)
        at = firsts.searchsorted(ids, "right") - 1
        safe = np.maximum(at, 0)
        missing: np.ndarray = (at < 0) | (ids > lasts[safe])
        return roots[safe], missing

    def firsts(self, ids: np.ndarray) -> np.ndarray:
        """The first vertex of the known range holding each of ``ids`` (each must be known:
        :meth:`lookup` found it)."""
        if self._arrays is None:
            self.lookup(ids[:0])
        assert self._arrays is not None
        starts = self._arrays[0]
        out: np.ndarray = starts[np.maximum(starts.searchsorted(ids, "right") - 1, 0)]
        return out
