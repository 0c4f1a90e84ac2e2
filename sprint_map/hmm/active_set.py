"""The active set: the components that hold belief, the live windows inside them, and where a
vertex lives in them."""

from __future__ import annotations

import math
from bisect import bisect_right
from collections.abc import Iterator

import numpy as np

from sprint_map.hmm import support
from sprint_map.hmm.decision import BeliefView
from sprint_map.hmm.graph import ComponentGraph
from sprint_map.hmm.transition import FLUSH_BELOW, ComponentTransition

_I64 = np.int64
_EMPTY = np.empty(0, dtype=_I64)
#: End trimming of a single window walks at most this many slots in Python before it switches to
#: one vectorised scan (a few slots per frame is the common case).
_WALK = 16


class ActiveComponent:
    """One active component: its transition, its belief (slot layout) and its live windows.

    Attributes
    ----------
    component_id : int
    trans : ComponentTransition
    x : ndarray of float64, shape (trans.n_slots,)
        Belief of every slot; 0 outside the windows (and in gutters). Normalised together with
        the other components and the sink after each update.
    mass : float
        Belief held by the component, as of the last update.
    n_windows : int
        Number of live windows (0: the component holds no belief yet).
    n_propagated : int
        Slots propagated by the last update (the input windows, edge targets included).
    pending : list of int
        Slots written this frame outside the windows (hits); they join the windows when the
        update finishes (:meth:`trim`).

    Notes
    -----
    The windows are kept as two int64 arrays ``lo``, ``hi``; a component with one window (the
    common case of a vehicle on one mapped road) also keeps them as the ints ``a``, ``b``, and
    its step is a handful of slice operations (:meth:`propagate`, :meth:`trim`).
    """

    __slots__ = ("_trim", "a", "b", "component_id", "hi", "live", "lo", "mass", "n_propagated",
                 "n_windows", "pending", "trans", "x")

    def __init__(self, trans: ComponentTransition) -> None:
        self.component_id = trans.graph.component_id
        self.trans = trans
        self.x = np.zeros(trans.n_slots)
        self.mass = 0.0
        self.lo = self.hi = _EMPTY
        self.a = self.b = 0
        self.n_windows = 0
        self.n_propagated = 0
        self.pending: list[int] = []
        self.live: np.ndarray | None = None
        self._trim: support.Trim | None = None

    @property
    def graph(self) -> ComponentGraph:
        """The component's arrays."""
        return self.trans.graph

    @property
    def n_live(self) -> int:
        """Slots in the live windows."""
        if self.n_windows == 1:
            return self.b - self.a
        return int((self.hi - self.lo).sum())

    def windows(self) -> tuple[np.ndarray, np.ndarray]:
        """The live windows ``[lo, hi)`` as sorted int64 arrays."""
        if self.n_windows == 1:
            return np.array([self.a], dtype=_I64), np.array([self.b], dtype=_I64)
        return self.lo, self.hi

    def set_windows(self, lo: np.ndarray, hi: np.ndarray) -> None:
        """Replace the windows (sorted, disjoint, at least ``trans.gap`` apart)."""
        self.lo, self.hi = lo, hi
        self.n_windows = n = lo.size
        if n == 1:
            self.a, self.b = int(lo[0]), int(hi[0])
        self.live = None

    def live_slots(self) -> np.ndarray:
        """All slots of the windows, ascending (cached until the windows change)."""
        if self.live is None:
            lo, hi = self.windows()
            self.live = support.ranges(lo, hi - lo)
        return self.live

    def propagate(self, flush: bool, scale: float) -> float:
        """One propagation step of the windows; return the overflow (mass for the sink).

        Parameters
        ----------
        flush : bool
            Zero beliefs below :data:`~sprint_map.hmm.transition.FLUSH_BELOW` first.
        scale : float
            ``1 - restart_prob - new_place_prob`` (the mass a step keeps).

        Notes
        -----
        One window without edges leaving it: one ``np.correlate`` over the window and one slice
        assignment, O(W (b - a)); the new mass follows from the mass balance (re-summed exactly
        on flush frames). Otherwise :meth:`ComponentTransition.propagate_windows`.
        """
        trans = self.trans
        x = self.x
        if self.n_windows == 1:
            a, b = self.a, self.b
            if not trans.has_edges or not trans.has_edges_from(a, b):
                if flush:
                    v = x[a:b]
                    np.putmask(v, v < FLUSH_BELOW, 0.0)
                y = np.correlate(x[a:b], trans.krev, "full")
                g = trans.gutter
                nb = b + g
                x[a:nb] = y
                spill = 0.0
                if g:
                    end = trans.seq_end_of(a)
                    if nb > end:
                        spill = math.fsum(y[end - a:].tolist())
                        x[end:nb] = 0.0
                        nb = end
                self.b = nb
                self.n_propagated = b - a
                self.live = None
                mass = scale * self.mass - spill
                if flush or mass < spill:
                    mass = math.fsum(x[a:nb].tolist()) if nb - a <= 64 else float(
                        x[a:nb].sum())
                self.mass = mass
                return spill
        lo, hi = self.windows()
        if flush:
            idx = self.live_slots()
            v = x[idx]
            np.putmask(v, v < FLUSH_BELOW, 0.0)
            x[idx] = v
        lo, hi, spill, mass, n_prop = trans.propagate_windows(x, lo, hi)
        self.set_windows(lo, hi)
        self.mass = mass
        self.n_propagated = n_prop
        return spill

    def trim(self, limit: float, interior: bool) -> float:
        """Fold the frame's new slots into the windows and trim them; return the mass trimmed.

        Slots below ``limit`` are cut from the ends of every window; with ``interior`` (or when
        the windows must be rebuilt anyway: several windows, new slots) windows are also split
        at runs of at least ``trans.gap`` slots below it. Nothing is normalised yet: the
        normaliser is applied by :meth:`normalise`, which also writes the cut slots to 0.

        Notes
        -----
        One window, no new slot, not ``interior``: a few scalar reads (O(slots trimmed));
        otherwise :func:`sprint_map.hmm.support.trim`, O(live).
        """
        pending = self.pending
        if self.n_windows == 1 and not pending and not interior:
            self._trim = None
            if limit <= 0.0:
                return 0.0
            x = self.x
            a, b = self.a, self.b
            if x.item(a) >= limit and x.item(b - 1) >= limit:
                return 0.0
            na, nb = _trim_ends(x, a, b, limit)
            cut = 0.0
            if na > a:
                cut += math.fsum(x[a:na].tolist()) if na - a <= 64 else float(x[a:na].sum())
                x[a:na] = 0.0
            if nb < b and nb > na:
                cut += math.fsum(x[nb:b].tolist()) if b - nb <= 64 else float(x[nb:b].sum())
                x[nb:b] = 0.0
            if na >= nb:  # the whole window was negligible
                self.set_windows(_EMPTY, _EMPTY)
                self.mass = 0.0
                return cut
            self.a, self.b = na, nb
            self.live = None
            self.mass -= cut
            return cut
        lo, hi = self.windows()
        if pending:
            new = np.array(pending, dtype=_I64)
            self.pending = []
            lo, hi = support.merge(np.concatenate((lo, new)), np.concatenate((hi, new + 1)),
                                   self.trans.gap)
        result = support.trim(self.x, lo, hi, limit, self.trans.gap)
        self._trim = result
        self.set_windows(result.lo, result.hi)
        self.mass -= result.trimmed
        return result.trimmed

    def normalise(self, inv: float) -> None:
        """Multiply the live belief by ``inv`` (and write the pending trim of :meth:`trim`)."""
        result = self._trim
        if result is None:
            v = self.x[self.a:self.b]
            v *= inv
        else:
            self._trim = None
            self.live = support.apply(result, self.x, inv)
        self.mass *= inv

    def view(self) -> BeliefView:
        """The belief in the form the decision code reads (with its live slots)."""
        if self.n_windows == 1:
            return BeliefView(self.trans.graph, self.trans.slot_first, self.x, a=self.a,
                              b=self.b)
        return BeliefView(self.trans.graph, self.trans.slot_first, self.x,
                          idx=self.live_slots())


def _trim_ends(x: np.ndarray, a: int, b: int, limit: float) -> tuple[int, int]:
    """The sub-window ``[na, nb)`` of ``[a, b)`` from the first to the last slot ``>= limit``.

    ``na >= nb`` when no slot reaches the limit. Walks in Python from both ends (a few slots
    per frame is the common case), switching to one vectorised scan after :data:`_WALK` slots.
    """
    i = a
    while i < b and x.item(i) < limit:
        i += 1
        if i - a == _WALK:
            above = np.flatnonzero(x[a:b] >= limit)
            if not above.size:
                return b, b
            return a + int(above[0]), a + int(above[-1]) + 1
    if i == b:
        return b, b
    j = b
    while x.item(j - 1) < limit:
        j -= 1
        if b - j == _WALK:
            above = np.flatnonzero(x[i:b] >= limit)
            return i, i + int(above[-1]) + 1
    return i, j


class ActiveSet:
    """Active components by id, plus a sorted index of their sequences' vertex ranges.

    Notes
    -----
    :meth:`locate` is O(log S_active) in pure Python (a bisect over the first vertex ids of the
    active sequences), so a hit inside the active set never reaches the graph source. The index
    is rebuilt lazily after the set changed, in O(S_active log S_active).
    """

    __slots__ = ("_dirty", "_ends", "_firsts", "_owners", "_slot0", "comps", "n_vertices")

    def __init__(self) -> None:
        self.comps: dict[int, ActiveComponent] = {}
        self.n_vertices = 0
        self._dirty = False
        self._firsts: list[int] = []
        self._ends: list[int] = []
        self._owners: list[ActiveComponent] = []
        self._slot0: list[int] = []

    def __len__(self) -> int:
        return len(self.comps)

    def __contains__(self, component_id: object) -> bool:
        return component_id in self.comps

    def __iter__(self) -> Iterator[ActiveComponent]:
        return iter(self.comps.values())

    def add(self, trans: ComponentTransition) -> ActiveComponent:
        """Activate a component with zero belief (ValueError if already active)."""
        cid = trans.graph.component_id
        if cid in self.comps:
            raise ValueError(f"component {cid} is already active")
        comp = self.comps[cid] = ActiveComponent(trans)
        self.n_vertices += trans.graph.n_vertices
        self._dirty = True
        return comp

    def remove(self, component_id: int) -> None:
        """Deactivate a component (its belief is dropped)."""
        comp = self.comps.pop(component_id)
        self.n_vertices -= comp.graph.n_vertices
        self._dirty = True

    def clear(self) -> None:
        """Deactivate everything."""
        self.comps.clear()
        self.n_vertices = 0
        self._dirty = True

    def locate(self, vertex_id: int) -> tuple[ActiveComponent, int] | None:
        """The active component holding ``vertex_id`` and its slot there, or None."""
        if self._dirty:
            self._rebuild()
        i = bisect_right(self._firsts, vertex_id) - 1
        if i >= 0 and vertex_id < self._ends[i]:
            return self._owners[i], self._slot0[i] + vertex_id - self._firsts[i]
        return None

    def _rebuild(self) -> None:
        comps = list(self.comps.values())
        self._dirty = False
        if not comps:
            self._firsts, self._ends, self._owners, self._slot0 = [], [], [], []
            return
        firsts = np.concatenate([c.graph.seq_first for c in comps])
        ends = firsts + np.concatenate([c.graph.seq_len for c in comps])
        slot0 = np.concatenate([c.trans.slot_first for c in comps])
        owner = np.repeat(np.arange(len(comps)), [c.graph.n_sequences for c in comps])
        order = np.argsort(firsts, kind="stable")
        self._firsts = firsts[order].tolist()
        self._ends = ends[order].tolist()
        self._slot0 = slot0[order].tolist()
        self._owners = [comps[i] for i in owner[order].tolist()]
