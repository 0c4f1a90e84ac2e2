"""Propagation: the forward window inside sequences, inter-sequence edges, the sink.

One transition model, two implementations that must agree to rounding:

* :class:`ComponentTransition` applies it to one component's compact belief vector with
  ``np.convolve`` over a "gutter" layout: every sequence is followed by ``W - 1`` zero slots, so
  mass that a sequence's window pushes past its last image lands in the gutter instead of the next
  sequence, and the gutter's total is the mass that goes to the sink. Only the ``W`` window
  weights are stored; this is the paper's O(W n) product with the Toeplitz part ``D``.
* :func:`full_transition_matrix` builds the same operator for the whole map as one scipy sparse
  matrix (the naive baseline and the reference of the tests).

The model (see ``docs/architecture.md`` ("The HMM")): a vertex ``u`` with out-edges ``u -> v_e`` of weight ``c_e``
sends ``x_u / R_u`` into its own window and ``x_u * beta * c_e / R_u`` into the window of
``v_e``, ``R_u = 1 + beta * sum_e c_e``; a window sends weight ``w[t]`` (normalised) ``t``
images ahead, or to the sink past the sequence end. The sink keeps its mass. Rows sum to one, so
propagation conserves mass. The filter then scales the propagated mass by
``1 - restart_prob - new_place_prob``; that factor is folded into the window here.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp

from sprint_map.hmm.config import HMMConfig
from sprint_map.hmm.graph import ComponentGraph

_I64 = np.int64

#: Every FLUSH_EVERY frames both filters set beliefs below FLUSH_BELOW to 0. Beliefs far behind
#: the vehicle decay geometrically and would otherwise reach subnormal floats, on which every
#: arithmetic operation is about 100x slower; the mass lost is below 1e-140.
FLUSH_EVERY = 16
FLUSH_BELOW = 1e-150


def window_kernel(config: HMMConfig) -> np.ndarray:
    """The normalised window ``w`` times ``1 - restart_prob - new_place_prob`` (float64, (W,))."""
    w = np.asarray(config.window, dtype=np.float64)
    return w * ((1.0 - config.restart_prob - config.new_place_prob) / w.sum())


class ComponentTransition:
    """The transition operator of one component, over a compact gutter layout.

    Parameters
    ----------
    graph : ComponentGraph
        The component.
    config : HMMConfig
        Window, edge weight, restart and new-place probabilities.

    Attributes
    ----------
    graph : ComponentGraph
    n_state : int
        Length of the belief vector: vertices plus ``W - 1`` gutter slots after every sequence
        but the last.
    slot_first : ndarray of int64, shape (S,)
        Slot of image 0 of each sequence (``seq_ids`` order).
    has_edges : bool
        Whether any edge carries mass (``beta > 0`` and a positive weight).
    simple : bool
        One sequence (or ``W = 1``) and no live edge: propagation is one convolution.
    krev : ndarray of float64, shape (W,)
        The scaled window reversed (``np.correlate`` with it is the convolution).
    ones : ndarray of float64, shape (n_state,)
        Used to sum the belief with one ``dot``.

    Notes
    -----
    Construction is O(n_vertices + S W + E). :meth:`propagate` is O(W n_state + E) with one
    numpy call for a one-sequence component without edges, three with several sequences and
    five more with edges.
    """

    __slots__ = ("_coef", "_dst", "_gsel", "_multi", "_rinv", "_src", "gutter", "graph",
                 "has_edges", "kernel", "krev", "n_state", "ones", "simple", "slot_first")

    def __init__(self, graph: ComponentGraph, config: HMMConfig) -> None:
        self.graph = graph
        self.kernel = window_kernel(config)
        # np.correlate with the reversed kernel is np.convolve without its Python-level checks.
        self.krev = np.ascontiguousarray(self.kernel[::-1])
        g = self.gutter = len(self.kernel) - 1
        n_seq = graph.n_sequences
        self.slot_first = graph.local_first + np.arange(n_seq, dtype=_I64) * g
        self.n_state = graph.n_vertices + (n_seq - 1) * g
        self._multi = n_seq > 1 and g > 0
        # x.dot(ones) sums a belief vector about 2x faster than x.sum() at the sizes that matter.
        self.ones = np.ones(self.n_state)
        if self._multi:
            ends = self.slot_first + graph.seq_len
            self._gsel: slice | np.ndarray = (ends[:, None] + np.arange(g, dtype=_I64)).ravel()
        else:
            self._gsel = slice(self.n_state, self.n_state + g)
        weights = graph.edge_weight * config.edge_weight
        live = weights > 0
        self.has_edges = bool(live.any())
        if self.has_edges:
            src = self.slot_first[graph.edge_src_seq[live]] + (
                graph.edge_src[live] - graph.seq_first[graph.edge_src_seq[live]])
            dst = self.slot_first[graph.edge_dst_seq[live]] + (
                graph.edge_dst[live] - graph.seq_first[graph.edge_dst_seq[live]])
            row = 1.0 + np.bincount(src, weights=weights[live], minlength=self.n_state)
            self._rinv = 1.0 / row
            self._src = src
            self._dst = dst
            self._coef = weights[live] * self._rinv[src]
        else:
            self._rinv = self._coef = np.empty(0)
            self._src = self._dst = np.empty(0, dtype=_I64)
        # One sequence and no live edge: propagation is a single convolution (the filter inlines
        # it on its hot path).
        self.simple = not self._multi and not self.has_edges

    def slots_of(self, vertex_ids: np.ndarray) -> np.ndarray:
        """Belief slot of each global vertex id of this component (O(m log S))."""
        vids = np.asarray(vertex_ids, dtype=_I64)
        seq = self.graph.seq_index(vids)
        if seq.size and seq.min() < 0:
            raise ValueError(f"vertex ids not in component {self.graph.component_id}")
        return self.slot_first[seq] + (vids - self.graph.seq_first[seq])

    def vertex_slots(self) -> np.ndarray:
        """Slots of all vertices, in compact local order (O(n_vertices))."""
        local = np.arange(self.graph.n_vertices, dtype=_I64)
        seq = np.searchsorted(self.graph.local_first, local, side="right") - 1
        return local + seq * self.gutter

    def propagate(self, x: np.ndarray) -> tuple[np.ndarray, float]:
        """Apply the (scaled) transition to belief ``x`` (length ``n_state``, zero gutters).

        Returns
        -------
        y : ndarray of float64, shape (n_state,)
            Propagated belief (a new array; gutters zero), already scaled by
            ``1 - restart_prob - new_place_prob``.
        overflow : float
            Mass that ran past sequence ends (goes to the sink), scaled likewise.
        """
        if self.has_edges:
            z = x * self._rinv
            z += np.bincount(self._dst, weights=x[self._src] * self._coef, minlength=self.n_state)
        else:
            z = x
        y = np.correlate(z, self.krev, "full")
        n = self.n_state
        if self._multi:
            gsel = self._gsel
            overflow = float(y[gsel].sum())
            y[gsel] = 0.0
        else:
            # Single sequence: the gutter is the W - 1 tail (empty for W = 1).
            overflow = math.fsum(y[n:].tolist())
        return y[:n], overflow


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
        ``1 - restart_prob - new_place_prob`` like :meth:`ComponentTransition.propagate`.

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
