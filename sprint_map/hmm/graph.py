"""The map as the HMM sees it: connected components as compact arrays, and where they come from.

A map's vertices are images; a sequence's vertices have contiguous global ids
(``seq_first[s] + image_id``). Sequences joined by inter-sequence edges form a component. The
filter only ever looks at components, through the :class:`GraphSource` protocol, so it knows
nothing of how the map is stored. :class:`MemoryGraphSource` is the in-memory implementation
used by tests and benchmarks; the map facade implements the protocol over LMDB.
"""

from __future__ import annotations

from bisect import bisect_right
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from sprint_map.util.union_find import UnionFind

__all__ = ["ComponentGraph", "EMPTY_IDS", "EMPTY_WEIGHTS", "GraphSource", "MemoryGraphSource"]

_I64 = np.int64


def _read_only(arr: np.ndarray) -> np.ndarray:
    arr.setflags(write=False)
    return arr


#: Shared read-only arrays: the zero first index of every single-sequence component, and the
#: edge arrays of every component without edges (``transition`` uses them too).
_ZERO1 = _read_only(np.zeros(1, dtype=_I64))
EMPTY_IDS = _read_only(np.zeros(0, dtype=_I64))
EMPTY_WEIGHTS = _read_only(np.zeros(0))


_I64_DTYPE = np.dtype(_I64)
_F64_DTYPE = np.dtype(np.float64)


def _as_array(name: str, value: object, dtype: np.dtype) -> np.ndarray:
    arr: np.ndarray
    # (``is``: the native dtypes are singletons; anything else takes the converting branch.)
    if type(value) is np.ndarray and value.dtype is dtype and value.flags.c_contiguous:
        arr = value  # (what sources pass: skip two conversions on the activation path)
    else:
        arr = np.ascontiguousarray(np.asarray(value, dtype=dtype))
    if arr.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class ComponentGraph:
    """Compact arrays for one connected component of the map.

    Built from ``component_id`` (any id; the filter only compares them), ``seq_ids`` (int64, S:
    the component's sequences, ascending), ``seq_first`` (global vertex id of each sequence's
    image 0), ``seq_len`` (images per sequence, >= 1), ``edge_src``, ``edge_dst`` (int64, E:
    global vertex ids of the directed inter-sequence edges, both ends in the component) and
    ``edge_weight`` (float64, E: match probability when the edge was made, finite, >= 0).

    Derived (read-only): ``n_vertices``; ``local_first`` (the compact local index of each
    sequence's image 0: sequences laid out in ``seq_ids`` order, ``local = local_first[s] +
    image_id``); ``edge_src_local``, ``edge_dst_local`` (edge ends as local indices);
    ``edge_src_seq``, ``edge_dst_seq`` (index into ``seq_ids`` of each end's sequence);
    ``adj_indptr``, ``adj_indices`` (undirected CSR adjacency over local indices, both edge
    directions: the vertices of a place).

    Raises ``ValueError`` on inconsistent arrays: shapes, unsorted or repeated sequence ids,
    empty or overlapping vertex ranges, an edge end outside the component, a negative or
    non-finite weight. Construction is O(S log S + E log E) time, O(n_vertices + E) memory.
    """

    component_id: int
    seq_ids: np.ndarray
    seq_first: np.ndarray
    seq_len: np.ndarray
    edge_src: np.ndarray
    edge_dst: np.ndarray
    edge_weight: np.ndarray

    def __post_init__(self) -> None:
        put = object.__setattr__
        put(self, "component_id", int(self.component_id))
        for name in ("seq_ids", "seq_first", "seq_len", "edge_src", "edge_dst"):
            put(self, name, _as_array(name, getattr(self, name), _I64_DTYPE))
        put(self, "edge_weight", _as_array("edge_weight", self.edge_weight, _F64_DTYPE))
        n_seq = len(self.seq_ids)
        if n_seq == 0:
            raise ValueError("a component has at least one sequence")
        if len(self.seq_first) != n_seq or len(self.seq_len) != n_seq:
            raise ValueError("seq_ids, seq_first and seq_len must have the same length")
        # (Array methods, not np.all / np.any: their Python wrappers cost several µs each, and
        # a component is built on every activation of a component that is not cached.)
        if n_seq > 1 and not (self.seq_ids[1:] > self.seq_ids[:-1]).all():
            raise ValueError("seq_ids must be sorted and unique")
        n_edges = len(self.edge_src)
        if len(self.edge_dst) != n_edges or len(self.edge_weight) != n_edges:
            raise ValueError("edge_src, edge_dst and edge_weight must have the same length")
        if n_seq == 1 and not n_edges:
            # One sequence, no edges: the component of a drive no other drive matched (every
            # component of Fig. 4). Built on each activation that misses the cache, so in
            # Python scalars and shared empty arrays rather than a dozen numpy calls.
            length = self.seq_len.item()
            if length < 1 or self.seq_first.item() < 0:
                raise ValueError(
                    "sequences must have length >= 1 and non-negative first vertex ids")
            put(self, "_by_first", _ZERO1)
            put(self, "_first_sorted", self.seq_first)
            put(self, "local_first", _ZERO1)
            put(self, "n_vertices", length)
            for name in ("edge_src_seq", "edge_dst_seq", "edge_src_local", "edge_dst_local",
                         "adj_indices"):
                put(self, name, EMPTY_IDS)
            put(self, "adj_indptr", _read_only(np.zeros(length + 1, dtype=_I64)))
            return
        if (self.seq_len < 1).any() or (self.seq_first < 0).any():
            raise ValueError("sequences must have length >= 1 and non-negative first vertex ids")
        if n_edges and (not np.isfinite(self.edge_weight).all() or self.edge_weight.min() < 0):
            raise ValueError("edge weights must be finite and >= 0")

        if n_seq == 1:  # the common small component: skip the sorts (activation cost)
            by_first = np.zeros(1, dtype=_I64)
            first_sorted = self.seq_first
        else:
            by_first = np.argsort(self.seq_first, kind="stable")
            first_sorted = self.seq_first[by_first]
            if (first_sorted[1:] < first_sorted[:-1] + self.seq_len[by_first][:-1]).any():
                raise ValueError("sequence vertex ranges overlap")
        put(self, "_by_first", by_first)
        put(self, "_first_sorted", first_sorted)
        local_first = np.zeros(n_seq, dtype=_I64)
        np.cumsum(self.seq_len[:-1], out=local_first[1:])
        put(self, "local_first", local_first)
        put(self, "n_vertices", int(self.seq_len.sum()))
        if not n_edges:
            empty = np.zeros(0, dtype=_I64)
            empty.setflags(write=False)
            for name in ("edge_src_seq", "edge_dst_seq", "edge_src_local", "edge_dst_local",
                         "adj_indices"):
                put(self, name, empty)
            put(self, "adj_indptr", np.zeros(self.n_vertices + 1, dtype=_I64))
            return

        src_seq = self.seq_index(self.edge_src)
        dst_seq = self.seq_index(self.edge_dst)
        if n_edges and (src_seq.min() < 0 or dst_seq.min() < 0):
            raise ValueError("an edge end is not a vertex of this component")
        put(self, "edge_src_seq", src_seq)
        put(self, "edge_dst_seq", dst_seq)
        src_local = local_first[src_seq] + (self.edge_src - self.seq_first[src_seq])
        dst_local = local_first[dst_seq] + (self.edge_dst - self.seq_first[dst_seq])
        put(self, "edge_src_local", src_local)
        put(self, "edge_dst_local", dst_local)

        # Undirected CSR: a place gathers vertices joined by an edge in either direction.
        ends = np.concatenate([src_local, dst_local])
        other = np.concatenate([dst_local, src_local])
        order = np.argsort(ends, kind="stable")
        indptr = np.zeros(self.n_vertices + 1, dtype=_I64)
        np.cumsum(np.bincount(ends, minlength=self.n_vertices), out=indptr[1:])
        put(self, "adj_indptr", indptr)
        put(self, "adj_indices", other[order])

    # Derived in __post_init__ (not constructor arguments).
    n_vertices: int = field(init=False, repr=False)
    local_first: np.ndarray = field(init=False, repr=False)
    edge_src_seq: np.ndarray = field(init=False, repr=False)
    edge_dst_seq: np.ndarray = field(init=False, repr=False)
    edge_src_local: np.ndarray = field(init=False, repr=False)
    edge_dst_local: np.ndarray = field(init=False, repr=False)
    adj_indptr: np.ndarray = field(init=False, repr=False)
    adj_indices: np.ndarray = field(init=False, repr=False)
    _by_first: np.ndarray = field(init=False, repr=False)
    _first_sorted: np.ndarray = field(init=False, repr=False)

    @property
    def n_sequences(self) -> int:
        """Number of sequences."""
        return len(self.seq_ids)

    @property
    def n_edges(self) -> int:
        """Number of directed edges."""
        return len(self.edge_src)

    @property
    def nbytes(self) -> int:
        """Bytes held by the arrays (what the component cache charges for it)."""
        arrays = (self.seq_ids, self.seq_first, self.seq_len, self.edge_src, self.edge_dst,
                  self.edge_weight, self.local_first, self.edge_src_seq, self.edge_dst_seq,
                  self.edge_src_local, self.edge_dst_local, self.adj_indptr, self.adj_indices,
                  self._by_first, self._first_sorted)
        return int(sum(a.nbytes for a in arrays)) + 256

    def seq_index(self, vertex_ids: np.ndarray) -> np.ndarray:
        """Index (into ``seq_ids``) of the sequence holding each global vertex id, -1 if none.

        Notes
        -----
        O(m log S) for m ids.
        """
        vids = np.asarray(vertex_ids, dtype=_I64)
        pos = np.searchsorted(self._first_sorted, vids, side="right") - 1
        clipped = np.maximum(pos, 0)
        seq = self._by_first[clipped]
        inside = (pos >= 0) & (vids < self.seq_first[seq] + self.seq_len[seq])
        return np.where(inside, seq, -1)

    def local_index(self, vertex_ids: np.ndarray) -> np.ndarray:
        """Compact local index of each global vertex id (ValueError if one is not in here).

        Notes
        -----
        O(m log S) for m ids.
        """
        vids = np.asarray(vertex_ids, dtype=_I64)
        seq = self.seq_index(vids)
        if seq.size and seq.min() < 0:
            raise ValueError(f"vertex ids not in component {self.component_id}")
        out: np.ndarray = self.local_first[seq] + (vids - self.seq_first[seq])
        return out

    def global_index(self, local: np.ndarray) -> np.ndarray:
        """Global vertex id of each compact local index.

        Notes
        -----
        O(m log S) for m indices.
        """
        loc = np.asarray(local, dtype=_I64)
        seq = np.searchsorted(self.local_first, loc, side="right") - 1
        out: np.ndarray = self.seq_first[seq] + (loc - self.local_first[seq])
        return out

    def vertex_ids(self) -> np.ndarray:
        """All global vertex ids, in compact local order (O(n_vertices))."""
        return self.global_index(np.arange(self.n_vertices, dtype=_I64))


@runtime_checkable
class GraphSource(Protocol):
    """Where the filter gets components from (the map facade implements it over LMDB)."""

    def components_of(self, vertex_ids: np.ndarray) -> np.ndarray:
        """Return the int64 component id of each global vertex id (ValueError if unknown)."""
        ...

    def load_component(self, component_id: int) -> ComponentGraph:
        """Return the compact arrays of one component."""
        ...


class MemoryGraphSource:
    """In-memory :class:`GraphSource` built from sequence lengths and edges.

    Sequence ``s`` (0-based, in the given order) gets the vertex ids
    ``sum(seq_lengths[:s]) ... + seq_lengths[s] - 1``, as the map facade assigns them. A
    component's id is the smallest sequence id in it.

    Parameters
    ----------
    seq_lengths : sequence of int
        Length (>= 1) of each sequence.
    edges : iterable of (int, int, float), optional
        Directed inter-sequence edges ``(src_vertex, dst_vertex, weight)``.

    Raises
    ------
    ValueError
        On a length < 1, an edge end that is not a vertex, a negative or non-finite weight.

    Notes
    -----
    Construction is O(S + E log E); ``components_of`` is O(m log S) for m ids;
    ``load_component`` is O(S_c + E_c) plus the :class:`ComponentGraph` construction.
    ``load_count`` counts loads (tests use it to check the cache).
    """

    def __init__(self, seq_lengths: Sequence[int],
                 edges: Iterable[tuple[int, int, float]] = ()) -> None:
        lengths = np.asarray(list(seq_lengths), dtype=_I64)
        if lengths.ndim != 1 or lengths.size == 0 or lengths.min() < 1:
            raise ValueError("seq_lengths must be a non-empty list of lengths >= 1")
        self.seq_len = lengths
        self.seq_first = np.zeros(len(lengths), dtype=_I64)
        np.cumsum(lengths[:-1], out=self.seq_first[1:])
        self._first_list: list[int] = self.seq_first.tolist()
        self.n_vertices = int(lengths.sum())
        edge_list = list(edges)
        src = np.array([e[0] for e in edge_list], dtype=_I64)
        dst = np.array([e[1] for e in edge_list], dtype=_I64)
        weight = np.array([e[2] for e in edge_list], dtype=np.float64)
        if src.size:
            if min(src.min(), dst.min()) < 0 or max(src.max(), dst.max()) >= self.n_vertices:
                raise ValueError("edge end outside the map")
            if not np.all(np.isfinite(weight)) or weight.min() < 0:
                raise ValueError("edge weights must be finite and >= 0")
        src_seq = self._seq_of(src)
        dst_seq = self._seq_of(dst)
        uf = UnionFind(len(lengths))
        for a, b in zip(src_seq.tolist(), dst_seq.tolist(), strict=True):
            uf.union(a, b)
        roots = np.array([uf.find(s) for s in range(len(lengths))], dtype=_I64)
        # Component id = smallest sequence id of the component (stable under edge order).
        comp_min = np.full(len(lengths), np.iinfo(np.int64).max, dtype=_I64)
        np.minimum.at(comp_min, roots, np.arange(len(lengths), dtype=_I64))
        self.seq_comp = comp_min[roots]
        self.seq_comp.setflags(write=False)  # (components_of may return a view of it)
        self._members: dict[int, np.ndarray] = {}
        order = np.argsort(self.seq_comp, kind="stable")
        comps, starts = np.unique(self.seq_comp[order], return_index=True)
        for c, members in zip(comps.tolist(), np.split(order, starts[1:]), strict=True):
            self._members[c] = members
        edge_comp = self.seq_comp[src_seq] if src.size else np.empty(0, dtype=_I64)
        edge_order = np.argsort(edge_comp, kind="stable")
        self._edges: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        if src.size:
            ecomps, estarts = np.unique(edge_comp[edge_order], return_index=True)
            bounds = np.append(estarts, len(edge_order))
            for i, c in enumerate(ecomps.tolist()):
                sel = edge_order[bounds[i]:bounds[i + 1]]
                self._edges[c] = (src[sel], dst[sel], weight[sel])
        self.load_count = 0

    def _seq_of(self, vids: np.ndarray) -> np.ndarray:
        return np.searchsorted(self.seq_first, vids, side="right") - 1

    def sequence_first(self, vertex_ids: np.ndarray) -> np.ndarray:
        """The first vertex id of each vertex's sequence (the drive rival's look-up;
        :func:`~sprint_map.hmm.observation.sequence_first_of`). O(m log S)."""
        vids = np.asarray(vertex_ids, dtype=_I64)
        out: np.ndarray = self.seq_first[np.maximum(self._seq_of(vids), 0)]
        return out

    @property
    def component_ids(self) -> list[int]:
        """Ids of all components, ascending."""
        return sorted(self._members)

    def components_of(self, vertex_ids: np.ndarray) -> np.ndarray:
        """Component id of each global vertex id (ValueError on an unknown id)."""
        vids = np.asarray(vertex_ids, dtype=_I64)
        if vids.shape == (1,):  # (the filter asks for one new hit at a time, mostly)
            v = vids.item()
            if not 0 <= v < self.n_vertices:
                raise ValueError("vertex id not in the map")
            s = bisect_right(self._first_list, v) - 1
            return self.seq_comp[s:s + 1]
        if vids.size and (vids.min() < 0 or vids.max() >= self.n_vertices):
            raise ValueError("vertex id not in the map")
        out: np.ndarray = self.seq_comp[self._seq_of(vids)]
        return out

    def load_component(self, component_id: int) -> ComponentGraph:
        """The compact arrays of component ``component_id`` (ValueError if unknown)."""
        members = self._members.get(int(component_id))
        if members is None:
            raise ValueError(f"no component {component_id}")
        self.load_count += 1
        src, dst, weight = self._edges.get(int(component_id), (EMPTY_IDS, EMPTY_IDS, EMPTY_WEIGHTS))
        if members.size == 1:  # (slices, not fancy indexing: most components are one drive)
            m = members.item()
            first, length = self.seq_first[m:m + 1], self.seq_len[m:m + 1]
        else:
            first, length = self.seq_first[members], self.seq_len[members]
        return ComponentGraph(component_id=int(component_id), seq_ids=members, seq_first=first,
                              seq_len=length, edge_src=src, edge_dst=dst, edge_weight=weight)

    def all_components(self) -> list[ComponentGraph]:
        """Every component (for :class:`FullGraphFilter`); O(n_vertices + E)."""
        return [self.load_component(c) for c in self.component_ids]
