"""The active set: the components that currently hold belief, and where a vertex lives in them."""

from __future__ import annotations

from bisect import bisect_right
from collections.abc import Iterator

import numpy as np

from sprint_map.hmm.decision import BeliefView
from sprint_map.hmm.graph import ComponentGraph
from sprint_map.hmm.transition import ComponentTransition


class ActiveComponent:
    """One active component: its transition and its belief vector (slot layout).

    Attributes
    ----------
    component_id : int
    trans : ComponentTransition
    x : ndarray of float64, shape (trans.n_state,)
        Belief of every slot (gutters 0); normalised together with the other components and
        the sink after each update.
    mass : float
        ``x.sum()`` as of the last update.
    """

    __slots__ = ("component_id", "mass", "trans", "x")

    def __init__(self, trans: ComponentTransition) -> None:
        self.component_id = trans.graph.component_id
        self.trans = trans
        self.x = np.zeros(trans.n_state)
        self.mass = 0.0

    @property
    def graph(self) -> ComponentGraph:
        """The component's arrays."""
        return self.trans.graph

    def view(self) -> BeliefView:
        """The belief in the form the decision code reads."""
        return BeliefView(self.trans.graph, self.trans.slot_first, self.x)


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
