"""The map's single-writer lock.

LMDB's own write lock makes a second writer *wait*; we want it refused at once, so writers take a
non-blocking ``flock`` on ``MAP/LOCK``. The kernel drops a flock when its holder dies (even by
SIGKILL), so a crashed writer never leaves a stale lock behind.
"""

from __future__ import annotations

import errno
import fcntl
import os
import stat
from pathlib import Path

from sprint_map.errors import MapCorruptError, MapLockedError, ReadOnlyMapError

__all__ = ["LOCK_NAME", "NOFOLLOW", "WriterLock", "open_lock_file", "writer_active"]

LOCK_NAME = "LOCK"
#: Never follow a link planted as ``MAP/LOCK`` (the writer would write into its target).
NOFOLLOW = os.O_NOFOLLOW | os.O_CLOEXEC


def open_lock_file(path: Path, flags: int) -> int:
    """Open ``path`` (a map's ``LOCK``) without following a symbolic link; refuse anything but
    a regular file with one link (a hard link could be a file outside the map). O(1).

    Raises
    ------
    MapCorruptError
        ``LOCK`` is a symbolic link, a hard link, or not a regular file.
    OSError
        Any other error of ``open`` (e.g. FileNotFoundError, PermissionError).
    """
    try:
        fd = os.open(path, flags | NOFOLLOW, 0o644)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise MapCorruptError(f"{path} is a symbolic link; a map's lock file must be a "
                                  "regular file inside the map (remove the link)") from None
        raise
    info = os.fstat(fd)
    if not stat.S_ISREG(info.st_mode) or info.st_nlink != 1:
        os.close(fd)
        what = "not a regular file" if not stat.S_ISREG(info.st_mode) else "a hard link"
        raise MapCorruptError(f"{path} is {what}; a map's lock file must be a regular file "
                              "of the map alone (remove it)")
    return fd


class WriterLock:
    """An exclusive, non-blocking, process-lifetime lock on ``directory/LOCK``."""

    def __init__(self, directory: Path) -> None:
        self.path = directory / LOCK_NAME
        self._fd: int | None = None

    def acquire(self) -> None:
        """Take the lock or raise :class:`MapLockedError` naming the holder's pid.

        Raises
        ------
        ReadOnlyMapError
            ``LOCK`` (or the map directory, to create it) is not writable by this process: the
            map can only be read (the permission error's own exit code, not an OS error's).
        """
        try:
            fd = open_lock_file(self.path, os.O_RDWR | os.O_CREAT)
        except PermissionError as exc:
            raise ReadOnlyMapError(f"map is not writable ({self.path}: {exc.strerror}); it can "
                                   "only be read") from None
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
        fd = open_lock_file(directory / LOCK_NAME, os.O_RDONLY)
    except (OSError, MapCorruptError):  # no LOCK file (no writer ever opened this map), not
        return False                    # readable, or not a lock file any writer could hold
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)  # closing drops our shared lock, if we got it
    return False
