"""The map a ``sprint-map view`` process shows: always the live generation.

A reader opened before a ``compact`` keeps the old generation (its files stay on disk while it
is open) and never sees a later commit. :class:`LiveMap` checks, before each read, whether the
map it holds is still the live generation (:meth:`SprintMap.is_current`: one small file read)
and if not opens the new one; the old one is closed, releasing its generation, as soon as no
read is in flight. Reads are :data:`~sprint_map.viewer.overview.Reader` calls, so the viewer's
summary uses it as its ``read``.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from typing import TypeVar

from sprint_map.map import SprintMap

__all__ = ["LiveMap"]

T = TypeVar("T")


class LiveMap:
    """A read-only map that follows compactions.

    ``on_switch(new_map)`` is called (under the lock) when a new generation is opened, so the
    owner can point at it. Cost per read: one ``CURRENT`` read; a switch costs one open.
    """

    def __init__(self, path: str | os.PathLike[str],
                 on_switch: Callable[[SprintMap], None] | None = None) -> None:
        self.path = path
        self.map = SprintMap.open(path, readonly=True)
        self.on_switch = on_switch
        self._lock = threading.Lock()
        self._in_flight = 0
        self._retired: list[SprintMap] = []

    def read(self, fn: Callable[[], T]) -> T:
        """Run ``fn`` (which reads ``self.map``) on the live generation."""
        with self._lock:
            if not self.map.is_current():
                fresh = SprintMap.open(self.path, readonly=True)
                self._retired.append(self.map)
                self.map = fresh
                if self.on_switch is not None:
                    self.on_switch(fresh)
            self._in_flight += 1
        try:
            return fn()
        finally:
            with self._lock:
                self._in_flight -= 1
                if not self._in_flight:
                    self._close_retired()

    def _close_retired(self) -> None:
        for old in self._retired:
            self.warnings.extend(old.warnings)
            old.close()
        self._retired.clear()

    @property
    def warnings(self) -> list[str]:
        return self.map.warnings

    def close(self) -> None:
        """Close the map and any generation still held."""
        with self._lock:
            self._close_retired()
            self.map.close()
