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
from sprint_map.hmm.transition import ComponentTransition

__all__ = ["ActiveComponent", "ActiveSet"]

_I64 = np.int64
_EMPTY = np.empty(0, dtype=_I64)
_add = np.add.reduce
_CANCEL = 1e-3


class ActiveComponent:
    """One active component: its transition, its belief (slot layout) and its live windows.

    - ``component_id``; ``trans``: its :class:`ComponentTransition`.
    - ``x`` (float64, ``trans.n_slots``): raw belief of every slot (the posterior is ``x`` times
      the filter's global normaliser); 0 outside the windows and in gutters. ``mass``: raw
      belief held, as of the last update.
    - ``n_windows``: live windows (0: no belief yet). ``lo``, ``hi`` (int64): the windows
      ``[lo, hi)`` (sorted, disjoint, at least ``trans.gap`` apart) when ``n_windows != 1``.
    - ``a``, ``b``, ``end``, ``shift``: when ``n_windows == 1``, the window ``[a, b)``, its
      sequence's end slot and the offset from vertex id to slot: the common case of a vehicle
      on one mapped road, stepped by a few slice operations inlined in :meth:`propagate`.
    - ``n_propagated``: slots propagated by the last update (input windows and edge targets).
    - ``pending``: slots written this frame outside the windows (hits); they join the windows
      when the update finishes (:meth:`settle`).
    """

    __slots__ = ("a", "b", "component_id", "end", "hi", "live", "lo", "mass", "n_propagated",
                 "n_windows", "pending", "shift", "trans", "x")

    def __init__(self, trans: ComponentTransition) -> None:
        self.component_id = trans.graph.component_id
        self.trans = trans
        self.x = np.zeros(trans.n_slots)
        self.mass = 0.0
        self.lo = self.hi = _EMPTY
        self.a = self.b = self.end = self.shift = 0
        self.n_windows = 0
        self.n_propagated = 0
        self.pending: list[int] = []
        self.live: np.ndarray | None = None

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
            self.end, self.shift = self.trans.seq_span_of(self.a)
        self.live = None

    def live_slots(self) -> np.ndarray:
        """All slots of the windows, ascending (cached until the windows change)."""
        if self.live is None:
            lo, hi = self.windows()
            self.live = support.ranges(lo, hi - lo)
        return self.live

    def propagate(self, flush_below: float, scale: float) -> float:
        """One propagation step of the windows; return the overflow (mass for the sink).

        Parameters
        ----------
        flush_below : float
            Zero beliefs below this first (0: no flush; see
            :data:`~sprint_map.hmm.transition.FLUSH_BELOW`).
        scale : float
            ``1 - restart_prob - new_place_prob``, the factor folded into the window (the
            one-window case uses it to know the new mass without summing).

        Notes
        -----
        One window with no edge leaving it (a vehicle on one mapped road; the common case) is
        one convolution and two slice writes, inlined here: per-call overhead is the whole cost
        of a step at this size. Otherwise :meth:`ComponentTransition.propagate_windows`,
        O(W live + edges leaving the windows).
        """
        x = self.x
        trans = self.trans
        if self.n_windows == 1:
            a, b = self.a, self.b
            if not trans.has_edges or not trans.has_edges_from(a, b):
                if flush_below:
                    v = x[a:b]
                    np.putmask(v, v < flush_below, 0.0)
                y = np.correlate(x[a:b], trans.krev, "full")
                nb = b + trans.spread
                self.live = None
                self.n_propagated = b - a
                end = self.end
                if nb <= end:
                    x[a:nb] = y
                    self.b = nb
                    # Propagation keeps mass (times scale): the new mass is known without
                    # summing (re-summed exactly on flush frames).
                    self.mass = float(_add(y)) if flush_below else scale * self.mass
                    return 0.0
                # What the window pushes past the sequence end goes to the sink (the gutter
                # slots from ``end`` on are never written: they stay 0).
                keep = end - a
                x[a:end] = y[:keep]
                spill = math.fsum(y[keep:].tolist())
                self.b = end
                mass = scale * self.mass - spill
                # The difference loses about log10(spill / mass) digits: sum what is left
                # when that could be more than three (and on flush frames).
                if flush_below or mass < _CANCEL * spill:
                    mass = float(_add(y[:keep]))
                self.mass = mass
                return spill
        lo, hi = self.windows()
        if flush_below:
            idx = self.live_slots()
            v = x[idx]
            np.putmask(v, v < flush_below, 0.0)
            x[idx] = v
        lo, hi, spill, mass, n_prop = trans.propagate_windows(x, lo, hi)
        self.set_windows(lo, hi)
        self.mass = mass
        self.n_propagated = n_prop
        return spill

    def settle(self, limit: float, lone: bool) -> float:
        """Fold the frame's new slots into the windows and trim them; return the mass trimmed.

        Parameters
        ----------
        limit : float
            Belief (in the units of ``x``) below which a slot is negligible; 0 trims nothing.
        lone : bool
            Whether to trim a single window without new slots too (the filter does it every
            ``TRIM_EVERY`` frames). Several windows, or new slots, are always trimmed: their
            windows are rebuilt anyway.

        Returns
        -------
        float
            Belief trimmed; the cut slots are set to 0.

        Notes
        -----
        Trimming cuts negligible slots from the ends of every window and splits windows at
        runs of at least ``trans.gap`` negligible slots (:func:`sprint_map.hmm.support.trim`).
        One window and no new slot: two numpy calls, plus two slice writes if its ends are cut;
        otherwise O(live) with about 30 numpy calls (merge, trim).
        """
        pending = self.pending
        x = self.x
        if pending and self.n_windows <= 1 and len(pending) == 1:
            # One new slot next to (or instead of) a single window: extend it in Python.
            slot = pending[0]
            gap = self.trans.gap
            if not self.n_windows:
                self.pending = []
                self.a, self.b, self.n_windows = slot, slot + 1, 1
                self.end, self.shift = self.trans.seq_span_of(slot)
                self.live = None
                pending = self.pending
            elif self.a - gap <= slot < self.b + gap and self.trans.seq_end_of(slot) == self.end:
                self.pending = []
                self.a, self.b = min(self.a, slot), max(self.b, slot + 1)
                self.live = None
                pending = self.pending
        if self.n_windows == 1 and not pending:
            if not lone or limit <= 0.0:
                return 0.0
            a, b = self.a, self.b
            above = (x[a:b] >= limit).nonzero()[0]
            n_above = above.size
            if n_above == b - a:
                return 0.0
            if n_above and int(above[-1]) - int(above[0]) + 1 == n_above:
                # One run: cut the ends only.
                na, nb = a + int(above[0]), a + int(above[-1]) + 1
                cut = _cut(x, a, na) + _cut(x, nb, b)
                self.a, self.b = na, nb
                self.live = None
                self.mass -= cut
                return cut
        lo, hi = self.windows()
        extra: np.ndarray | None = None
        if pending:
            extra = np.array(pending, dtype=_I64)
            self.pending = []
        new_lo, new_hi, live, trimmed = support.trim(x, lo, hi, limit, self.trans.gap, extra)
        self.set_windows(new_lo, new_hi)
        self.live = live
        self.mass -= trimmed
        return trimmed

    def rescale(self, factor: float) -> None:
        """Multiply the live belief by ``factor`` (O(live))."""
        if self.n_windows == 1:
            v = self.x[self.a:self.b]
            v *= factor
        elif self.n_windows:
            idx = self.live_slots()
            self.x[idx] *= factor
        self.mass *= factor

    def view(self, scale: float = 1.0) -> BeliefView:
        """The belief for the decision code: live slots, and ``scale`` (posterior = x * scale)."""
        if self.n_windows == 1:
            return BeliefView(self.trans.graph, self.trans.slot_first, self.x, a=self.a,
                              b=self.b, scale=scale)
        return BeliefView(self.trans.graph, self.trans.slot_first, self.x,
                          idx=self.live_slots(), scale=scale)


def _cut(x: np.ndarray, start: int, stop: int) -> float:
    """Zero ``x[start:stop]`` and return what it held."""
    if stop <= start:
        return 0.0
    part = x[start:stop]
    held = math.fsum(part.tolist()) if stop - start <= 64 else float(part.sum())
    part[:] = 0.0
    return held


class ActiveSet:
    """Active components by id, plus a sorted index of their sequences' vertex ranges.

    Notes
    -----
    :meth:`locate` is O(log S_active) in pure Python (a bisect over the first vertex ids of the
    active sequences), so a hit inside the active set never reaches the graph source. The index
    is rebuilt lazily after a component joined, in O(S_active log S_active); a component that
    leaves is only dropped from ``comps`` (:meth:`locate` skips index entries whose owner is no
    longer active), so pruning never rebuilds it.
    """

    __slots__ = ("_arrays", "_dirty", "_distinct", "_ends", "_firsts", "_owners", "_slot0",
                 "comps", "n_vertices")

    def __init__(self) -> None:
        self.comps: dict[int, ActiveComponent] = {}
        self.n_vertices = 0
        self._dirty = False
        self._firsts: list[int] = []
        self._ends: list[int] = []
        self._owners: list[ActiveComponent] = []
        self._slot0: list[int] = []
        #: The index as arrays (firsts, ends, slot0 and each entry's owner as a number), for
        #: :meth:`locate_many` (made on first use after a rebuild).
        self._arrays: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        #: The distinct owners of the index's entries, in the order the owner numbers count.
        self._distinct: list[ActiveComponent] = []

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
            owner = self._owners[i]
            if self.comps.get(owner.component_id) is owner:
                return owner, self._slot0[i] + vertex_id - self._firsts[i]
        return None

    def locate_many(self, vertex_ids: np.ndarray
                    ) -> list[tuple[ActiveComponent, np.ndarray, np.ndarray]] | None:
        """:meth:`locate` of many vertices at once: per active component holding some of them,
        their slots there and their positions in ``vertex_ids`` (both in ``vertex_ids``'
        order); None if any vertex is not in the active set.

        Notes
        -----
        O(n log S_active), about 10 numpy calls whatever ``n``.
        """
        firsts, ends, slot0, owner_of = self._index_arrays()
        ids = np.asarray(vertex_ids, dtype=_I64)
        if not ids.size:
            return []
        i = firsts.searchsorted(ids, "right") - 1
        if bool((i < 0).any()) or not bool((ids < ends[i]).all()):
            return None
        slots = slot0[i] + ids - firsts[i]
        owner = owner_of[i]
        if bool((owner == owner[0]).all()):  # the common case: one component
            groups = [(int(i[0]), slots, np.arange(ids.size, dtype=_I64))]
        else:
            at = np.argsort(owner, kind="stable")
            cuts = (np.diff(owner[at]) != 0).nonzero()[0] + 1
            # (a stable sort keeps each group's positions ascending)
            groups = [(int(i[part[0]]), slots[part], part) for part in np.split(at, cuts)]
        out = []
        for row, group_slots, positions in groups:
            comp = self._owners[row]
            if self.comps.get(comp.component_id) is not comp:
                return None  # an index entry of a component that left
            out.append((comp, group_slots, positions))
        return out

    def locate_each(self, vertex_ids: np.ndarray) -> list[tuple[ActiveComponent, int] | None]:
        """:meth:`locate` of each of ``vertex_ids`` (int64), in one search.

        Notes
        -----
        O(n log S_active): about 10 numpy calls and one Python pass over the ``n`` answers.
        """
        firsts, ends, slot0, owner_of = self._index_arrays()
        ids = np.asarray(vertex_ids, dtype=_I64)
        if not firsts.size:
            return [None] * ids.size
        i = firsts.searchsorted(ids, "right") - 1
        np.maximum(i, 0, out=i)
        inside = ((ids >= firsts[i]) & (ids < ends[i])).tolist()
        comps = self.comps
        # (the index keeps the entries of components removed since it was built)
        owners = [c if comps.get(c.component_id) is c else None for c in self._distinct]
        return [(owner, slot) if ok and (owner := owners[o]) is not None else None
                for o, slot, ok in zip(owner_of[i].tolist(), (slot0[i] + ids - firsts[i]).tolist(),
                                       inside, strict=True)]

    def _index_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The index as arrays (range firsts, ends, first slots, owner numbers into
        ``_distinct``), made on first use after a rebuild."""
        if self._dirty:
            self._rebuild()
        if self._arrays is None:
            self._distinct = list(dict.fromkeys(self._owners))
            index = {id(o): n for n, o in enumerate(self._distinct)}
            self._arrays = (np.asarray(self._firsts, dtype=_I64),
                            np.asarray(self._ends, dtype=_I64),
                            np.asarray(self._slot0, dtype=_I64),
                            np.asarray([index[id(o)] for o in self._owners], dtype=_I64))
        return self._arrays

    def _rebuild(self) -> None:
        comps = list(self.comps.values())
        self._dirty = False
        self._arrays = None
        if sum(c.graph.n_sequences for c in comps) <= 64:
            # Few sequences: sorting Python tuples beats the numpy round trip.
            rows = sorted((first, first + length, slot, i)
                          for i, c in enumerate(comps)
                          for first, length, slot in c.trans.ranges)
            self._firsts = [r[0] for r in rows]
            self._ends = [r[1] for r in rows]
            self._slot0 = [r[2] for r in rows]
            self._owners = [comps[r[3]] for r in rows]
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
