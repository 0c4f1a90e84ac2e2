"""The server process's heap: its start-up objects kept out of the garbage collector's way,
and the collector's pauses measured.

A full collection (CPython's generation 2) walks every object the collector tracks while it
holds the GIL, so every frame in flight waits for it. The server's heap after start-up is
~85,000-100,000 such objects (FastAPI, pydantic, starlette, NumPy, SciPy, FAISS's SWIG modules,
the app, the open map), almost all of them alive until the process ends; walking them took
15 ms on a quiet core and 30 ms beside the batcher thread, and one such pause in a run of 16
vehicles delayed the whole batch in flight: 16 frames of 1,600, i.e. the run's p99 (see
``docs/benchmarks.md``, "Service").

:func:`settle` collects once and then freezes what is left (``gc.freeze``): those objects move
to a permanent generation that later collections skip, so a full collection walks only what
was allocated since (sessions, their decisions, requests in progress): a fraction of a
millisecond while the server serves. Objects allocated later are collected as before. The cost:
a start-up object that later becomes unreachable *only through a reference cycle* is never
freed; start-up objects are modules, classes, the app and the map, which live as long as the
process. So :func:`settle` is for a process that is the server (``sprint-map serve``), not for a
test process that creates services in passing.

:class:`GcPauses` times every collection (``gc.callbacks``) by generation, for the metrics
(``sprint_map_gc_pause_seconds``): the pauses every frame in flight waited for.
"""

from __future__ import annotations

import bisect
import gc
import time
from typing import Any

from sprint_map.server.metrics import Labels

__all__ = ["GC_BUCKETS", "GcPauses", "settle"]

#: Pause buckets in seconds (0.1 ms .. 1 s): young collections take tens of microseconds.
GC_BUCKETS = (0.0001, 0.0002, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0)


def settle() -> int:
    """Collect everything collectable now, then freeze the rest out of later collections.

    Returns
    -------
    int
        The objects frozen (``gc.get_freeze_count()``).

    Notes
    -----
    One full collection, O(tracked objects) (~15-30 ms on the server's start-up heap), once.
    """
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


class GcPauses:
    """Counts the garbage collector's pauses by generation (see the module docstring).

    The counts are written only by the collector's callback and never under a lock: a
    collection can start inside any allocation, also one made while a metric's lock is held,
    and collections never overlap (one runs at a time, holding the GIL), so the callback is
    their only writer. :meth:`series` copies them for rendering.
    """

    def __init__(self, buckets: tuple[float, ...] = GC_BUCKETS) -> None:
        self.buckets = tuple(buckets)
        self._series = {str(g): [0.0] * (len(self.buckets) + 2) for g in range(3)}
        self._started = 0.0
        self._installed = False

    def install(self) -> None:
        """Start timing collections (idempotent)."""
        if not self._installed:
            gc.callbacks.append(self._callback)
            self._installed = True

    def uninstall(self) -> None:
        """Stop timing collections (idempotent)."""
        if self._installed:
            gc.callbacks.remove(self._callback)
            self._installed = False

    def _callback(self, phase: str, info: dict[str, Any]) -> None:
        if phase == "start":
            self._started = time.perf_counter()
            return
        pause = time.perf_counter() - self._started
        series = self._series.get(str(info.get("generation")))
        if series is not None:
            series[bisect.bisect_left(self.buckets, pause)] += 1
            series[-1] += pause

    def count(self, generation: int) -> int:
        """Collections of ``generation`` timed so far."""
        return int(sum(self._series[str(generation)][:-1]))

    def series(self) -> dict[Labels, list[float]]:
        """``{(("generation", g),): [count per bucket..., above the last, sum of pauses]}``."""
        return {(("generation", g),): list(s) for g, s in self._series.items()}
