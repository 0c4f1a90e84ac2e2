"""The map's single-writer lock.

LMDB's own write lock makes a second writer *wait*; we want it refused at once, so writers take a
non-blocking ``flock`` on ``MAP/LOCK``. The kernel drops a flock when its holder dies (even by
SIGKILL), so a crashed writer never leaves a stale lock behind.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

from sprint_map.errors import MapLockedError

LOCK_NAME = "LOCK"


class WriterLock:
    """An exclusive, non-blocking, process-lifetime lock on ``directory/LOCK``."""

    def __init__(self, directory: Path) -> None:
        self.path = directory / LOCK_NAME
        self._fd: int | None = None

    def acquire(self) -> None:
        """Take the lock or raise :class:`MapLockedError` naming the holder's pid."""
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise MapLockedError(
                f"map is locked by another writer (pid {holder}): {self.path}"
            ) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    @property
    def held(self) -> bool:
        return self._fd is not None


def writer_active(directory: Path) -> bool:
    """Whether some process holds the writer lock of the map at ``directory`` right now.

    Probes with a shared, non-blocking ``flock`` on a descriptor of our own, released at once.
    Only meaningful from a process that is not itself the writer (a second open file
    description of the same process conflicts with its own exclusive lock too).
    """
    try:
        fd = os.open(directory / LOCK_NAME, os.O_RDONLY)
    except OSError:  # no LOCK file: no writer ever opened this map, or it is not readable
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)  # closing drops our shared lock, if we got it
    return False
