"""Propagation: the forward window inside sequences, inter-sequence edges, the sink.

One transition model, two implementations that must agree to rounding:

* :class:`ComponentTransition` applies it to one component's belief in a "gutter" slot layout:
  every sequence is followed by ``max(W - 1, 1)`` zero slots, so mass that a sequence's window pushes past
  its last image lands in the gutter instead of the next sequence, and the gutter's total is the
  mass that goes to the sink. Only the ``W`` window weights are stored; this is the paper's
  O(W n) product with the Toeplitz part ``D``. :meth:`ComponentTransition.propagate_windows`
  applies it to the *live support* only (windows of slots, :mod:`sprint_map.hmm.support`) with
  one ``np.correlate`` over the gathered windows (the whole component is the case where every
  sequence is one window).
* :func:`full_transition_matrix` builds the same operator for the whole map as one scipy sparse
  matrix (the naive baseline and the reference of the tests).

The model (``docs/hmm.md``, "The model"): a vertex ``u`` with out-edges ``u -> v_e`` of
weight ``c_e`` sends ``x_u / R_u`` into its own window and ``x_u * beta * c_e / R_u`` into the
window of ``v_e``, ``R_u = 1 + beta * sum_e c_e``; a window sends weight ``w[t]`` (normalised)
``t`` images ahead, or to the sink past the sequence end. The sink keeps its mass. Rows sum to
one, so propagation conserves mass. The filter then scales the propagated mass by
``1 - restart_prob - new_place_prob``; that factor is folded into the window here.
"""

from __future__ import annotations

import math
from bisect import bisect_left, bisect_right
from collections.abc import Sequence
from functools import lru_cache

import numpy as np
import scipy.sparse as sp

from sprint_map.hmm.config import HMMConfig
from sprint_map.hmm.graph import EMPTY_IDS, EMPTY_WEIGHTS, ComponentGraph
from sprint_map.hmm.support import insert_sorted, merge, merge_gap, ranges

__all__ = ["ComponentTransition", "FLUSH_BELOW", "FLUSH_EVERY", "PullOperator",
           "full_transition_matrix", "parts_pull_operator", "window_kernel"]

_I64 = np.int64
_FIRST = np.zeros(1, dtype=np.int64)


#: Every FLUSH_EVERY frames both filters set beliefs below FLUSH_BELOW to 0. Beliefs far behind
#: the vehicle decay geometrically and would otherwise reach subnormal floats, on which every
#: arithmetic operation is about 100x slower; the mass lost is below 1e-140.
FLUSH_EVERY = 16
FLUSH_BELOW = 1e-150


def window_kernel(config: HMMConfig) -> np.ndarray:
    """The normalised window ``w`` times ``1 - restart_prob - new_place_prob`` (float64, (W,))."""
    return _kernels(config)[0].copy()


def _kernels(config: HMMConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``window_kernel``, its reverse and its tails (``tails[r]``: the share of a window past
    a sequence's end ``r`` slots ahead, ``0 <= r < W``), read-only, once per config
    (components share them)."""
    # Keyed by the three fields it reads: hashing the whole frozen config costs more than the
    # rest of a component's set-up.
    return _kernels_of(config.window, config.restart_prob, config.new_place_prob)


@lru_cache(maxsize=16)
def _kernels_of(window: tuple[float, ...], restart_prob: float, new_place_prob: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    w = np.asarray(window, dtype=np.float64)
    kernel = w * ((1.0 - restart_prob - new_place_prob) / w.sum())
    krev = np.ascontiguousarray(kernel[::-1])
    steps = np.arange(len(kernel), dtype=_I64)
    # (summed row by row as a row of zeros then the tail, as the sums it stands for)
    tails = np.where(steps >= steps[:, None], kernel, 0.0).sum(axis=1)
    for array in (kernel, krev, tails):
        array.setflags(write=False)
    return kernel, krev, tails


class ComponentTransition:
    """The transition operator of one component (``graph``, with ``config``'s window, edge
    weight, restart and new-place probabilities), over a gutter slot layout.

    Attributes (read-only):

    - ``gutter``: ``g = max(W - 1, 1)`` zero slots after every sequence: room for what a window
      at a sequence end pushes past it, and at least ``gap``, so windows of two sequences never
      touch (with ``W = 1`` and no gutter they would merge, and the end clip would send the
      second one's mass to the sink). ``spread``: ``W - 1``, how far one step moves mass.
    - ``n_state``: vertices plus ``g`` after every sequence but the last (:meth:`propagate`);
      ``n_slots``: ``n_state + g``, a belief vector for :meth:`propagate_windows`.
    - ``slot_first``, ``seq_end`` (int64, S): slot of image 0 of each sequence (``seq_ids``
      order), one past its last; ``ranges``: ``(first vertex id, length, first slot)`` of each.
    - ``gap``: smallest distance between two windows (:func:`.support.merge_gap`).
    - ``has_edges``: whether any edge carries mass; ``edge_src``, ``edge_dst``, ``edge_coef``:
      the live edges as slots, sorted by source, each with its share ``beta c_e / R_u`` of the
      source's mass; ``krev``: the scaled window reversed (``np.correlate`` with it convolves).

    Construction is O(S + E log E), plus O(n_vertices) for the reciprocal row sums when the
    component has edges. :meth:`propagate_windows` is O(W live + edges leaving the windows),
    never O(n_vertices).
    """

    __slots__ = ("_edge_src_list", "_first_list", "_rinv", "_tails", "edge_coef", "edge_dst",
                 "edge_src", "gap", "graph", "gutter", "has_edges", "kernel", "krev", "n_slots",
                 "n_state", "ranges", "seq_end", "slot_first", "spread")

    def __init__(self, graph: ComponentGraph, config: HMMConfig) -> None:
        self.graph = graph
        # Correlating with the reversed kernel is np.convolve without its Python-level checks.
        self.kernel, self.krev, self._tails = _kernels(config)
        self.spread = len(self.kernel) - 1
        g = self.gutter = self.gap = merge_gap(len(self.kernel))
        n_seq = graph.n_sequences
        if n_seq == 1:
            self.slot_first = graph.local_first
        else:
            self.slot_first = graph.local_first + np.arange(n_seq, dtype=_I64) * g
        if n_seq == 1:
            length = graph.n_vertices
            self.seq_end = np.array([length], dtype=_I64)
            self._first_list: list[int] = [0]
            self.ranges = [(graph.seq_first.item(), length, 0)]
        else:
            self.seq_end = self.slot_first + graph.seq_len
            self._first_list = self.slot_first.tolist()
            self.ranges = list(zip(graph.seq_first.tolist(), graph.seq_len.tolist(),
                                   self._first_list, strict=True))
        self.n_state = graph.n_vertices + (n_seq - 1) * g
        self.n_slots = self.n_state + g
        if graph.n_edges:
            weights = graph.edge_weight * config.edge_weight
            live = weights > 0
            self.has_edges = bool(live.any())
        else:  # (most components: skip three numpy calls on every activation)
            self.has_edges = False
        if self.has_edges:
            src = self.slot_first[graph.edge_src_seq[live]] + (
                graph.edge_src[live] - graph.seq_first[graph.edge_src_seq[live]])
            dst = self.slot_first[graph.edge_dst_seq[live]] + (
                graph.edge_dst[live] - graph.seq_first[graph.edge_dst_seq[live]])
            row = 1.0 + np.bincount(src, weights=weights[live], minlength=self.n_slots)
            self._rinv = 1.0 / row
            order = np.argsort(src, kind="stable")
            self.edge_src = src[order]
            self.edge_dst = dst[order]
            self.edge_coef = weights[live][order] * self._rinv[self.edge_src]
            self._edge_src_list: list[int] = self.edge_src.tolist()
        else:
            self._rinv = self.edge_coef = EMPTY_WEIGHTS
            self.edge_src = self.edge_dst = EMPTY_IDS
            self._edge_src_list = []

    def slots_of(self, vertex_ids: np.ndarray) -> np.ndarray:
        """Belief slot of each global vertex id of this component (O(m log S))."""
        at, slots = self.held_slots(vertex_ids)
        if at.size != np.size(vertex_ids):
            raise ValueError(f"vertex ids not in component {self.graph.component_id}")
        return slots

    def held_slots(self, vertex_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The positions in ``vertex_ids`` of those this component holds, and their belief
        slots (O(m log S))."""
        vids = np.asarray(vertex_ids, dtype=_I64)
        seq = self.graph.seq_index(vids)
        at = (seq >= 0).nonzero()[0]
        seq = seq[at]
        slots: np.ndarray = self.slot_first[seq] + (vids[at] - self.graph.seq_first[seq])
        return at, slots

    def vertex_slots(self) -> np.ndarray:
        """Slots of all vertices, in compact local order (O(n_vertices))."""
        local = np.arange(self.graph.n_vertices, dtype=_I64)
        seq = np.searchsorted(self.graph.local_first, local, side="right") - 1
        return local + seq * self.gutter

    def vertex_of_slots(self, slots: np.ndarray) -> np.ndarray:
        """Global vertex id of each (vertex) slot (O(m log S))."""
        sl = np.asarray(slots, dtype=_I64)
        seq = np.searchsorted(self.slot_first, sl, side="right") - 1
        out: np.ndarray = self.graph.seq_first[seq] + (sl - self.slot_first[seq])
        return out

    def seq_end_of(self, slot: int) -> int:
        """One past the last slot of the sequence holding ``slot`` (O(log S), pure Python)."""
        return self.seq_span_of(slot)[0]

    def seq_span_of(self, slot: int) -> tuple[int, int]:
        """``(end, shift)`` of the sequence holding ``slot`` (O(log S), pure Python).

        ``end`` is one past its last slot; ``shift`` is slot minus global vertex id in it.
        """
        first_vertex, length, first_slot = self.ranges[bisect_right(self._first_list, slot) - 1]
        return first_slot + length, first_slot - first_vertex

    def has_edges_from(self, lo: int, hi: int) -> bool:
        """Whether a live edge leaves a slot of ``[lo, hi)`` (O(log E), pure Python)."""
        src = self._edge_src_list
        i = bisect_left(src, lo)
        return i < len(src) and src[i] < hi

    def propagate_windows(self, x: np.ndarray, lo: np.ndarray, hi: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray, float, float, int]:
        """Propagate the belief held in windows ``[lo, hi)`` of ``x``, in place.

        ``x`` (float64, ``n_slots``) is the belief in slot layout, 0 outside the windows; ``lo``,
        ``hi`` (int64) are sorted windows, each inside one sequence, at least :attr:`gap` apart.

        Returns ``(lo, hi, overflow, mass, n_propagated)``: the windows after the step (grown by
        ``W - 1``, clipped at sequence ends, joined by one window per edge target outside them,
        merged where closer than :attr:`gap`; ``x`` is 0 outside them again), the mass that ran past
        sequence ends (scaled like the belief; it goes to the sink), the belief left in the windows,
        and the slots propagated (the input windows, edge targets included).

        O(W live + edges leaving the windows), about 25 numpy calls whatever the number of windows:
        the windows are gathered into one compact vector, each followed by its own ``W - 1`` zero
        slots, convolved once and scattered back; edges leaving them are found by two binary
        searches in the source-sorted edge list.
        """
        g = self.spread
        n_edges = 0
        if self.has_edges:
            e_lo = self.edge_src.searchsorted(lo)
            counts = self.edge_src.searchsorted(hi) - e_lo
            n_edges = int(counts.sum())
            if n_edges:
                eidx = ranges(e_lo, counts, n_edges)
                dst = self.edge_dst[eidx]
                moved = x[self.edge_src[eidx]] * self.edge_coef[eidx]
                # Edge targets outside the windows open windows of their own.
                pos = lo.searchsorted(dst, "right") - 1
                if not np.all((pos >= 0) & (dst < hi[pos])):
                    lo, hi = merge(np.concatenate((lo, dst)), np.concatenate((hi, dst + 1)),
                                   self.gap)
                    pos = lo.searchsorted(dst, "right") - 1
        lens = hi - lo
        n_prop = int(lens.sum())
        seg = lens + g
        total = n_prop + g * lo.size
        out = ranges(lo, seg, total)
        z = x[out]
        if self.has_edges:
            z *= self._rinv[out]
            if n_edges:
                start = seg.cumsum() - seg
                z += np.bincount(start[pos] + (dst - lo[pos]), weights=moved, minlength=total)
        # Each window's output lands in [lo, hi + g): its own slots and the g free slots after
        # it (the next window is at least g away, or a gutter follows), never another window.
        y = np.correlate(z, self.krev, "full")[:total]
        x[out] = y
        mass = float(y.sum())
        overflow = 0.0
        hi = hi + g
        if g:
            end = self.seq_end[self.slot_first.searchsorted(lo, "right") - 1]
            over = (hi > end).nonzero()[0]
            if over.size:
                for j in over.tolist():
                    e, h = int(end[j]), int(hi[j])
                    overflow += math.fsum(x[e:h].tolist())
                    x[e:h] = 0.0
                hi = np.minimum(hi, end)
                mass -= overflow
        # Grown windows of one sequence may now be closer than the gap: merge them. (They are
        # still sorted and each ends before the next starts, since they were ``gap`` apart
        # and grew by ``g <= gap``: a run of close ones spans its first start to its last end,
        # which is what ``merge`` gives, without its sort.)
        if lo.size > 1:
            apart = lo[1:] >= hi[:-1] + self.gap
            if not apart.all():
                first = np.concatenate((_FIRST, apart.nonzero()[0] + 1))
                last = np.concatenate((first[1:] - 1, [lo.size - 1]))
                lo, hi = lo[first], hi[last]
        return lo, hi, overflow, mass, n_prop


    def pull(self, slots: np.ndarray, m_slots: np.ndarray, m_vals: np.ndarray, m_sink: float
             ) -> np.ndarray:
        """The adjoint of the propagation (the backward step of the smoother).

        For every source slot ``u`` of ``slots`` return ``sum_j A(u, j) m(j)``: the expected
        value of ``m`` one step after ``u`` under the same scaled transition that
        :meth:`propagate_windows` applies (own window, edges, overflow to the sink), where ``m``
        is ``m_vals`` at the sorted slots ``m_slots``, 0 at every other vertex slot, and
        ``m_sink`` at the sink.

        Notes
        -----
        O((|slots| + E_out) W log |m_slots|) for the ``E_out`` edges leaving ``slots``:
        binary searches in ``m_slots``, never a pass over the component.
        """
        slots = np.asarray(slots, dtype=_I64)
        kernel = self.kernel
        steps = np.arange(len(kernel), dtype=_I64)
        n_m = len(m_slots)

        def ahead(origin: np.ndarray) -> np.ndarray:
            # m over the window of each origin, weighted by the kernel (sink past the end).
            end = self.seq_end[self.slot_first.searchsorted(origin, "right") - 1]
            tgt = origin[:, None] + steps
            if n_m:
                pos = np.minimum(m_slots.searchsorted(tgt), n_m - 1)
                vals = np.where(m_slots[pos] == tgt, m_vals[pos], 0.0)
            else:
                vals = np.zeros(tgt.shape)
            vals = np.where(tgt < end[:, None], vals, m_sink)
            return np.asarray(vals @ kernel)

        out = ahead(slots)
        if self.has_edges and slots.size:
            out *= self._rinv[slots]
            e_lo = self.edge_src.searchsorted(slots)
            counts = self.edge_src.searchsorted(slots, "right") - e_lo
            n_edges = int(counts.sum())
            if n_edges:
                eidx = ranges(e_lo, counts, n_edges)
                owner = np.repeat(np.arange(slots.size, dtype=_I64), counts)
                moved = ahead(self.edge_dst[eidx]) * self.edge_coef[eidx]
                out += np.bincount(owner, weights=moved, minlength=slots.size)
        return out


    def pull_operator(self, slots: np.ndarray, m_slots: np.ndarray) -> PullOperator:
        """:meth:`pull` from sorted ``slots`` onto ``m_slots`` as a linear operator, built once
        and applied to many ``m`` (the fixed-lag smoother pulls every pair of frames ``L``
        times).

        ``pull(slots, m_slots, m_vals, m_sink)`` equals ``op.apply(m_vals, m_sink)`` (to
        rounding: the sums are taken in another order). :func:`parts_pull_operator` with
        this one part.

        Notes
        -----
        Built in O((|slots| + E_out) W + |m_slots| log |slots|), about 30 numpy calls, no
        search per target: see :class:`PullOperator`.
        """
        return parts_pull_operator([(self, slots)], [(self, m_slots)])

    def _edges_leaving(self, slots: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(1 / R_u of each slot, owner, origin, coef)`` of the live edges leaving sorted
        ``slots`` (``owner``: the position in ``slots`` of each edge's source; ``origin``: its
        target slot). The component must have edges. O((n + E_out) log E)."""
        factor = self._rinv[slots]
        e_lo = self.edge_src.searchsorted(slots)
        counts = self.edge_src.searchsorted(slots, "right") - e_lo
        n_edges = int(counts.sum())
        if not n_edges:
            return factor, EMPTY_IDS, EMPTY_IDS, EMPTY_WEIGHTS
        eidx = ranges(e_lo, counts, n_edges)
        owner = np.repeat(np.arange(slots.size, dtype=_I64), counts)
        return factor, owner, self.edge_dst[eidx], self.edge_coef[eidx]

    def _spilled(self, origin: np.ndarray, factor: np.ndarray | None, *,
                 ordered: bool = False) -> tuple[np.ndarray, np.ndarray] | None:
        """The origins whose window reaches past their sequence's end (positions in
        ``origin``, ascending) and the share of each window past it (to the sink), times
        ``factor`` (``ordered``: the origins are sorted); None when no window reaches an end.
        O(n); O(log n) for sorted origins of one sequence.
        """
        width = len(self.kernel)
        if not origin.size:
            return None
        if ordered and len(self.ranges) == 1:
            _, end, _ = self.ranges[0]  # (one sequence: its first slot is 0, its end its length)
            if int(origin[-1]) + width <= end:
                return None  # (the last origin not near the end)
            first = int(origin.searchsorted(end - width + 1))  # (the near ones: a tail)
            near = np.arange(first, origin.size, dtype=_I64)
            shares = self._tails[end - origin[first:]]
        else:
            room = self.seq_end[self.slot_first.searchsorted(origin, "right") - 1] - origin
            near = (room < width).nonzero()[0]
            if not near.size:
                return None
            shares = self._tails[room[near]]
        if factor is not None:
            shares *= factor[near]
        return near, shares


def slot_bases(transitions: Sequence[ComponentTransition]) -> list[int]:
    """Where each component's slots start in one slot space: past the slots of the ones
    before it plus ``W``, so that no window reaches from one into the next. O(components)."""
    bases = [0]
    for trans in transitions[:-1]:
        bases.append(bases[-1] + trans.n_slots + len(trans.kernel))
    return bases


def slot_space(parts: Sequence[tuple[ComponentTransition, np.ndarray]]) -> np.ndarray:
    """The sorted slots of ``parts`` (a component's transition and its sorted slots each)
    laid in one slot space (:func:`slot_bases`), ascending, as :func:`parts_pull_operator`
    lays its sources. O(live), one numpy call per part."""
    if not parts:
        return EMPTY_IDS
    bases = slot_bases([trans for trans, _ in parts])
    return _concat([slots + at if at else np.asarray(slots, dtype=_I64)
                    for (_, slots), at in zip(parts, bases, strict=True)])


def parts_pull_operator(sources: Sequence[tuple[ComponentTransition, np.ndarray]],
                        targets: Sequence[tuple[ComponentTransition, np.ndarray]], *,
                        source_space: np.ndarray | None = None,
                        target_space: np.ndarray | None = None) -> PullOperator:
    """One :class:`PullOperator` from the ``targets`` parts laid end to end onto the
    ``sources`` parts laid end to end (a part: a component's transition and sorted slots, one
    part per component on each side): each source part pulls (:meth:`ComponentTransition.pull`)
    from the target part of its component, if any, else only sends its share past its
    sequences' ends to the sink. All must share one window (ValueError otherwise).

    ``source_space``, if the caller keeps it: :func:`slot_space` of the sources;
    ``target_space``: that of the targets, given only when their components are the sources'
    in the same order (the targets then lie in the sources' space).

    Applied, it gives float for float what each source part's own
    :meth:`ComponentTransition.pull_operator` gives on its target part.

    Notes
    -----
    All slots lie in one space (:func:`slot_bases`): one layout, one search for the targets.
    O((live + E_out) W + targets log live), about 20 numpy calls plus one per part (more for
    a part with edges or near a sequence's end).
    """
    if not sources:
        return PullOperator(0, 0, np.ones(1), EMPTY_IDS, EMPTY_IDS, EMPTY_IDS, None,
                            EMPTY_IDS, EMPTY_IDS, EMPTY_WEIGHTS, EMPTY_IDS, EMPTY_WEIGHTS)
    kernel = sources[0][0].kernel
    width = len(kernel)
    base: dict[int, int] = {}  # component -> offset of its slots
    n = 0
    src: list[np.ndarray] = []
    spill_rows: list[np.ndarray] = []  # the rows that send a share to the sink ...
    spill_shares: list[np.ndarray] = []  # ... and their shares
    factors: list[tuple[int, np.ndarray]] = []  # (first row, 1 / R_u) of the parts with edges
    owners: list[np.ndarray] = []
    e_origins: list[np.ndarray] = []
    coefs: list[np.ndarray] = []
    for (trans, part), at in zip(sources, slot_bases([trans for trans, _ in sources]),
                                 strict=True):
        if trans.kernel is not kernel and not np.array_equal(trans.kernel, kernel):
            raise ValueError("operators with different windows cannot be joined")
        slots = (part if isinstance(part, np.ndarray) and part.dtype == _I64
                 else np.asarray(part, dtype=_I64))
        base[trans.graph.component_id] = at
        factor = None
        if trans.has_edges and slots.size:
            factor, owner, e_origin, coef = trans._edges_leaving(slots)
            factors.append((n, factor))
        spill = trans._spilled(slots, factor, ordered=True)
        if factor is not None and e_origin.size:
            e_spill = trans._spilled(e_origin, coef)
            if e_spill is not None:  # (each source's own share, then its edges' shares)
                sink = np.zeros(slots.size)
                if spill is not None:
                    sink[spill[0]] = spill[1]
                sink += np.bincount(owner[e_spill[0]], weights=e_spill[1], minlength=slots.size)
                rows = sink.nonzero()[0]
                spill = rows, sink[rows]
            owners.append(owner + n)
            e_origins.append(e_origin + at)
            coefs.append(coef)
        if source_space is None:
            src.append(slots + at if at else slots)
        if spill is not None:
            spill_rows.append(spill[0] + n if n else spill[0])
            spill_shares.append(spill[1])
        n += slots.size
    # (a target part without a source part is put below every window)
    if target_space is not None:
        m_all = target_space
    else:
        m_all = _concat([np.asarray(m_slots, dtype=_I64)
                         + base.get(trans.graph.component_id, -trans.n_slots - width)
                         for trans, m_slots in targets]) if targets else EMPTY_IDS
    slots_all = source_space if source_space is not None else _concat(src)
    e_all = _concat(e_origins) if e_origins else EMPTY_IDS
    origin = slots_all if not e_all.size else insert_sorted(slots_all, e_all)
    size, lo, hi, shift, place = _window_layout(origin, width)
    src_place, e_place = place, EMPTY_IDS
    if e_all.size:
        src_place = place[origin.searchsorted(slots_all)]
        e_place = place[origin.searchsorted(e_all)]
    m_sel, m_place = EMPTY_IDS, EMPTY_IDS
    if size and m_all.size:
        block = lo.searchsorted(m_all, "right") - 1
        np.maximum(block, 0, out=block)
        m_sel = ((m_all >= lo[block]) & (m_all < hi[block])).nonzero()[0]
        m_place = m_all[m_sel] + shift[block[m_sel]]
    return PullOperator(n, size, kernel, m_sel, m_place, src_place,
                        _factors(n, factors) if factors else None,
                        _concat(owners) if owners else EMPTY_IDS, e_place,
                        _concat(coefs) if coefs else EMPTY_WEIGHTS,
                        _concat(spill_rows) if spill_rows else EMPTY_IDS,
                        _concat(spill_shares) if spill_shares else EMPTY_WEIGHTS)


def _factors(n: int, blocks: list[tuple[int, np.ndarray]]) -> np.ndarray:
    """``n`` factors, 1 but for the blocks given (each its first row and values)."""
    if len(blocks) == 1 and blocks[0][1].size == n:
        return blocks[0][1]
    out = np.ones(n)
    for first, values in blocks:
        out[first:first + values.size] = values
    return out


def _concat(arrays: list[np.ndarray]) -> np.ndarray:
    """``np.concatenate`` without the copy of a single array."""
    return arrays[0] if len(arrays) == 1 else np.concatenate(arrays)


def _window_layout(origin: np.ndarray, width: int
                   ) -> tuple[int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A compact layout of the windows ``[o, o + width)`` of sorted ``origin``: origins
    closer than ``width`` share a block ``[lo, hi)`` (its first origin to its last plus
    ``width``); a slot ``s`` of block ``b`` sits at ``s + shift[b]``.

    Returns ``(size, lo, hi, shift, place)``, ``place`` the place of each origin. O(n), about
    12 numpy calls.
    """
    n = origin.size
    if not n:
        return 0, EMPTY_IDS, EMPTY_IDS, EMPTY_IDS, EMPTY_IDS
    breaks = ((origin[1:] - origin[:-1]) >= width).nonzero()[0] + 1
    lo = origin[np.concatenate(([0], breaks))]
    hi = origin[np.concatenate((breaks - 1, [n - 1]))] + width
    lens = hi - lo
    ends = lens.cumsum()
    shift = ends - lens - lo
    block = np.zeros(n, dtype=_I64)
    block[breaks] = 1
    place = origin + shift[block.cumsum()]
    return int(ends[-1]), lo, hi, shift, place


class PullOperator:
    """A :meth:`ComponentTransition.pull` fixed in its source and target slots.

    ``apply(m, m_sink)`` scatters the targets' values into a compact layout of the sources'
    windows (``m_place``; those of ``m_sel``, the targets any window reaches, each times
    ``m_weight`` if set), correlates the layout once with the window ``kernel`` and reads each
    source's window at ``src_place`` (times ``factor``: ``1 / R_u`` when the component has
    edges) and each edge's target window at ``e_place`` (times ``e_coef``, added to row
    ``e_owner``); ``spill_shares``: the share of each row of ``spill_rows`` (the sources
    whose windows reach past their sequence's end) that leaves it, times ``m_sink``.

    Notes
    -----
    O(layout size W) per application, about 8 numpy calls; the layout holds at most
    ``(n + E_out) W`` slots. :func:`parts_pull_operator` builds one for several components.
    """

    __slots__ = ("_layout", "e_coef", "e_owner", "e_place", "factor", "kernel", "m_place",
                 "m_sel", "m_weight", "n", "size", "spill_rows", "spill_shares", "spills",
                 "src_place")

    def __init__(self, n: int, size: int, kernel: np.ndarray, m_sel: np.ndarray,
                 m_place: np.ndarray, src_place: np.ndarray, factor: np.ndarray | None,
                 e_owner: np.ndarray, e_place: np.ndarray, e_coef: np.ndarray,
                 spill_rows: np.ndarray, spill_shares: np.ndarray,
                 m_weight: np.ndarray | None = None) -> None:
        self.n, self.size, self.kernel = n, size, kernel
        self.m_sel, self.m_place, self.m_weight = m_sel, m_place, m_weight
        self.src_place, self.factor = src_place, factor
        self.e_owner, self.e_place, self.e_coef = e_owner, e_place, e_coef
        self.spill_rows, self.spill_shares = spill_rows, spill_shares
        #: Whether any source reaches past its sequence's end.
        self.spills = bool(spill_rows.size)
        #: The layout, made on first use: only ``m_place`` is ever written, the rest stays 0.
        self._layout: np.ndarray | None = None

    def weigh_targets(self, weight: np.ndarray) -> None:
        """Multiply each target's value by ``weight`` (one per target slot) before the
        pull (the smoother folds in the next frame's likelihood ratios)."""
        w = weight[self.m_sel]
        self.m_weight = w if self.m_weight is None else self.m_weight * w

    def apply(self, m_vals: np.ndarray, m_sink: float) -> np.ndarray:
        """The pulled values of the ``n`` source slots."""
        if not self.size:
            spilled = np.zeros(self.n)
            spilled[self.spill_rows] = self.spill_shares * m_sink
            return spilled
        z = self._layout
        if z is None:
            z = self._layout = np.zeros(self.size)
        if self.m_sel.size:
            v = m_vals[self.m_sel]
            if self.m_weight is not None:
                v *= self.m_weight
            z[self.m_place] = v
        y = np.correlate(z, self.kernel, "valid")  # y[p] = sum_k kernel[k] z[p + k]
        out: np.ndarray = y[self.src_place]
        if self.factor is not None:
            out *= self.factor
        if self.e_owner.size:
            out += np.bincount(self.e_owner, weights=self.e_coef * y[self.e_place],
                               minlength=self.n)
        if self.spills:
            out[self.spill_rows] += self.spill_shares * m_sink
        return out


def full_transition_matrix(graphs: Sequence[ComponentGraph], config: HMMConfig,
                           offsets: Sequence[int]) -> sp.csr_matrix:
    """The scaled transition of the whole map as a CSR matrix acting on ``[x; sink]``.

    Parameters
    ----------
    graphs : sequence of ComponentGraph
        All components; component ``i``'s compact local index ``l`` is state ``offsets[i] + l``.
    config : HMMConfig
    offsets : sequence of int
        First state of each component; the sink is state ``n = sum(n_vertices)``.

    Returns
    -------
    scipy.sparse.csr_matrix, shape (n + 1, n + 1)
        ``A`` with ``A @ [x; s]`` the propagated belief (column = source state), scaled by
        ``1 - restart_prob - new_place_prob`` like :meth:`ComponentTransition.propagate_windows`.

    Notes
    -----
    O(W (n + E)) time and memory; the matrix has about ``W (n + E) + 1`` non-zeros.
    """
    kernel = window_kernel(config)
    n = int(sum(g.n_vertices for g in graphs))
    sink = n
    rows: list[np.ndarray] = []
    cols: list[np.ndarray] = []
    vals: list[np.ndarray] = []
    for graph, off in zip(graphs, offsets, strict=True):
        seq_of = np.repeat(np.arange(graph.n_sequences, dtype=_I64), graph.seq_len)
        local = np.arange(graph.n_vertices, dtype=_I64)
        image = local - graph.local_first[seq_of]
        length = graph.seq_len[seq_of]
        weights = graph.edge_weight * config.edge_weight
        live = weights > 0
        src = graph.edge_src_local[live]
        dst = graph.edge_dst_local[live]
        row_sum = 1.0 + np.bincount(src, weights=weights[live], minlength=graph.n_vertices)
        rinv = 1.0 / row_sum
        # Sources of window mass: every vertex (own window) and every live edge (dst's window).
        origin = np.concatenate([local, dst])  # whose window
        source = np.concatenate([local, src])  # whose mass
        share = np.concatenate([rinv, weights[live] * rinv[src]])
        o_image = image[origin]
        o_len = length[origin]
        for t, wt in enumerate(kernel.tolist()):
            if wt == 0.0:
                continue
            inside = o_image + t < o_len
            rows.append(np.where(inside, off + origin + t, sink))
            cols.append(off + source)
            vals.append(share * wt)
    # The sink keeps its mass (scaled like everything else by 1 - eps - nu).
    rows.append(np.array([sink], dtype=_I64))
    cols.append(np.array([sink], dtype=_I64))
    vals.append(np.array([kernel.sum()]))
    matrix = sp.coo_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n + 1, n + 1))
    return matrix.tocsr()
