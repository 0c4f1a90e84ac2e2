"""MapGate: the readers-writer lock between answering frames and committing drives.

The server holds one writable map shared by every session (py-lmdb cannot open an environment
twice in one process). Frames read it concurrently (LMDB snapshots, FAISS searches, which are
safe together); the commit's short critical section is exclusive: the LMDB write transaction
(which may grow the map, which LMDB allows only with no transaction open in the process), adding
the rows to the FAISS index (``add`` is not safe beside ``search``), and telling the live filters
which components changed, so that no frame sees the new map before its filter was told.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["MapGate"]


class MapGate:
    """A writer-preferring readers-writer lock (a waiting commit stops new frames entering).

    Notes
    -----
    ``exclusive`` records how long it held the gate (``last_exclusive_s``): the time frames
    were held up by a commit.
    """

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._readers = 0
        self._writer = False
        self._writers_waiting = 0
        self.last_exclusive_s = 0.0

    @contextmanager
    def shared(self) -> Iterator[None]:
        """Read the map (any number at once)."""
        with self._cond:
            while self._writer or self._writers_waiting:
                self._cond.wait()
            self._readers += 1
        try:
            yield
        finally:
            with self._cond:
                self._readers -= 1
                if not self._readers:
                    self._cond.notify_all()

    @contextmanager
    def exclusive(self) -> Iterator[None]:
        """Change the map (alone): waits for the frames in progress, blocks new ones."""
        with self._cond:
            self._writers_waiting += 1
            try:
                while self._writer or self._readers:
                    self._cond.wait()
            finally:
                self._writers_waiting -= 1
            self._writer = True
        start = time.perf_counter()
        try:
            yield
        finally:
            self.last_exclusive_s = time.perf_counter() - start
            with self._cond:
                self._writer = False
                self._cond.notify_all()
