"""A byte-bounded LRU cache of components, so a component is read from the source only when needed."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Iterable

from sprint_map.hmm.graph import ComponentGraph

__all__ = ["ComponentCache", "SharedComponentCache"]


class ComponentCache:
    """Least-recently-used cache of :class:`ComponentGraph` bounded by a byte budget.

    Parameters
    ----------
    budget_bytes : int
        Upper bound on the summed :attr:`ComponentGraph.nbytes` of the cached components. One
        component larger than the budget is still returned by :meth:`get` (the filter needs it)
        but is not kept.

    Attributes
    ----------
    hits, misses : int
        Counters of :meth:`get` calls answered from the cache / by the loader.

    Notes
    -----
    ``get`` is O(1) on a hit and O(1) amortised plus the loader's cost on a miss. The cache
    holds no other reference to the source; the map facade calls :meth:`invalidate` with the
    ids of components that changed (a merge, a sequence added) so stale arrays are never served.
    A component the filter keeps active is also referenced by the filter, so evicting it here
    frees nothing until it leaves the active set.
    """

    def __init__(self, budget_bytes: int) -> None:
        if not isinstance(budget_bytes, int) or budget_bytes < 0:
            raise ValueError("budget_bytes must be an integer >= 0")
        self.budget_bytes = budget_bytes
        self._items: OrderedDict[int, ComponentGraph] = OrderedDict()
        self._nbytes = 0
        self.hits = 0
        self.misses = 0

    def __len__(self) -> int:
        return len(self._items)

    def __contains__(self, component_id: object) -> bool:
        return component_id in self._items

    @property
    def nbytes(self) -> int:
        """Bytes currently charged to the cache (<= ``budget_bytes``)."""
        return self._nbytes

    def get(self, component_id: int,
            loader: Callable[[int], ComponentGraph]) -> ComponentGraph:
        """Return component ``component_id``, calling ``loader(component_id)`` on a miss.

        Raises
        ------
        ValueError
            If the loader returns a component with another id.
        """
        items = self._items
        graph = items.get(component_id)
        if graph is not None:
            items.move_to_end(component_id)
            self.hits += 1
            return graph
        self.misses += 1
        graph = loader(component_id)
        if graph.component_id != component_id:
            raise ValueError(f"loader returned component {graph.component_id} for {component_id}")
        size = graph.nbytes
        if size <= self.budget_bytes:
            items[component_id] = graph
            self._nbytes += size
            while self._nbytes > self.budget_bytes:
                _, old = items.popitem(last=False)
                self._nbytes -= old.nbytes
        return graph

    def invalidate(self, component_ids: Iterable[int]) -> None:
        """Forget the given components (unknown ids are ignored)."""
        for cid in component_ids:
            old = self._items.pop(int(cid), None)
            if old is not None:
                self._nbytes -= old.nbytes

    def clear(self) -> None:
        """Forget every component."""
        self._items.clear()
        self._nbytes = 0


class SharedComponentCache(ComponentCache):
    """A :class:`ComponentCache` shared by filters in several threads (the service's
    sessions), so a component is loaded (and held) once.

    A lock serialises the cache's bookkeeping and the loads (two filters asking for the same
    component load it once). Components are immutable (read-only arrays), so filters share
    them safely. Whoever changes the map invalidates the changed components here before a
    filter can see the change (the service's commit writer, under its exclusive gate).
    """

    def __init__(self, budget_bytes: int) -> None:
        super().__init__(budget_bytes)
        self._lock = threading.RLock()

    def get(self, component_id: int,
            loader: Callable[[int], ComponentGraph]) -> ComponentGraph:
        with self._lock:
            return super().get(component_id, loader)

    def invalidate(self, component_ids: Iterable[int]) -> None:
        with self._lock:
            super().invalidate(component_ids)

    def clear(self) -> None:
        with self._lock:
            super().clear()
