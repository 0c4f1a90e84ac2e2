"""Durable file primitives: fsync'd writes, atomic publication of whole files, and the file seam.

A failed fsync fails the operation and is never retried: after a failed fsync the kernel may have
marked the dirty pages clean, so a retry could report success for lost data ("fsyncgate").

Every file-system call the map makes on its own files (descriptor shards, index files, their
directories; not LMDB, which does its own I/O and fsync) goes through the functions of this module.
They are the map's whole failure surface, and a test seam: :func:`set_file_hook` installs a
function called before each call, which may raise to inject an I/O error or a simulated power cut
(see :mod:`sprint_map.testing.faults`). With no hook installed a call costs one ``None`` test.
"""

from __future__ import annotations

import contextlib
import errno
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sprint_map.errors import StorageIOError

__all__ = ["FILE_OPS", "FileHook", "PARTIAL_SUFFIX", "fsync", "fsync_dir", "fsync_file",
           "open_for_write", "publish", "publish_bytes", "remove_partials", "remove_tree",
           "replace", "set_file_hook", "truncate", "unlink", "write_at"]

PARTIAL_SUFFIX = ".partial"

#: The calls announced to the hook, with what ``info`` holds for each:
#: ``create`` a new file ({}); ``write`` ``data`` at ``offset`` (``data`` None: an opaque
#: writer, e.g. FAISS, writes the whole file); ``truncate`` to ``size``; ``fsync`` a file;
#: ``fsync_dir`` a directory; ``replace`` the file by renaming it to ``dst``; ``unlink``.
FILE_OPS = ("create", "write", "truncate", "fsync", "fsync_dir", "replace", "unlink")

#: ``hook(op, path, info)``; see :func:`set_file_hook`.
FileHook = Callable[[str, Path, dict[str, Any]], None]
_hook: FileHook | None = None


def set_file_hook(hook: FileHook | None) -> FileHook | None:
    """Install ``hook`` (None removes it); return the previous one.

    ``hook(op, path, info)`` runs before each file-system call on the map's files (``op`` in
    :data:`FILE_OPS`); raising ``OSError`` from it makes that call fail as the OS would.
    """
    global _hook
    previous, _hook = _hook, hook
    return previous


def _announce(op: str, path: str | os.PathLike[str], **info: Any) -> None:
    if _hook is not None:
        _hook(op, Path(path), info)


# --- the seam: one function per file-system call ------------------------------------------


def open_for_write(path: Path) -> int:
    """Open (creating if absent) ``path`` for writing; return the descriptor."""
    if _hook is not None and not path.exists():
        _announce("create", path)
    return os.open(path, os.O_WRONLY | os.O_CREAT, 0o644)


def write_at(fd: int, path: Path, data: memoryview, offset: int) -> None:
    """Write all of ``data`` at ``offset`` of the open file ``fd`` (``path``, for the hook)."""
    _announce("write", path, fd=fd, data=data, offset=offset)
    written = 0
    while written < len(data):
        written += os.pwrite(fd, data[written:], offset + written)


def truncate(path: Path, size: int, fd: int | None = None) -> None:
    """Cut ``path`` (through ``fd`` if given) to ``size`` bytes."""
    _announce("truncate", path, size=size)
    if fd is None:
        os.truncate(path, size)
    else:
        os.ftruncate(fd, size)


def fsync(fd: int, path: Path) -> None:
    """Make the data of the open file ``fd`` durable. A failure is final: never retry it."""
    _announce("fsync", path, fd=fd)
    os.fsync(fd)


def fsync_file(path: Path) -> None:
    """Make the data of the closed file ``path`` durable."""
    fd = os.open(path, os.O_RDONLY)
    try:
        fsync(fd, path)
    finally:
        os.close(fd)


def fsync_dir(path: Path) -> None:
    """Make a directory's entries (created, renamed, removed files) durable."""
    _announce("fsync_dir", path)
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def replace(src: Path, dst: Path) -> None:
    """Rename ``src`` over ``dst`` atomically (durable once the directory is fsynced)."""
    _announce("replace", src, dst=dst)
    os.replace(src, dst)


def unlink(path: Path) -> None:
    """Remove ``path`` if it exists (durable once the directory is fsynced)."""
    _announce("unlink", path)
    path.unlink(missing_ok=True)


def remove_tree(path: Path) -> None:
    """Remove the directory ``path`` and all it holds (durable once its parent is fsynced)."""
    _announce("unlink", path)
    shutil.rmtree(path)


# --- whole files ------------------------------------------------------------------------------


def publish(path: Path, write: Callable[[Path], Any], expected_size: int | None = None) -> None:
    """Write ``path`` atomically: ``write(partial)``, fsync, ``os.replace``, fsync the directory.

    For the map's own files (under its writer lock) and reports; a file the user names as an
    output goes through :class:`sprint_map.util.output.Output`. ``write`` receives the
    temporary path (anything there before is removed first) and must create the file there. Readers see either the
    old file or the complete new one, never a torn one. Give ``expected_size`` when ``write``
    may fail silently: FAISS, for one, reports a failed write (``EFBIG``, ``ENOSPC``) only on
    stderr when it closes the file, and returns as if it had succeeded.

    Raises
    ------
    StorageIOError
        On any error of the write, the fsync, the rename or the directory fsync; the temporary
        file is removed and nothing is retried.
    """
    partial = path.with_name(path.name + PARTIAL_SUFFIX)
    try:
        # Whatever is at the partial's name (a killed run's file, a planted link) goes first:
        # unlink never follows a link, so ``write`` creates a new file, never writes through.
        partial.unlink(missing_ok=True)
        _announce("create", partial)
        _announce("write", partial, data=None, offset=0)
        write(partial)
        if expected_size is not None and partial.stat().st_size != expected_size:
            raise OSError(errno.EIO, f"short write ({partial.stat().st_size} of "
                                     f"{expected_size} bytes)")
        fsync_file(partial)
        replace(partial, path)
        fsync_dir(path.parent)
    except OSError as exc:
        with contextlib.suppress(OSError):  # else the next writer's open removes it
            partial.unlink(missing_ok=True)
        raise StorageIOError(f"cannot write {path}: {exc.strerror or exc}") from exc


def publish_bytes(path: Path, data: bytes) -> None:
    """:func:`publish` a small file holding ``data``."""

    def write(partial: Path) -> None:
        fd = os.open(partial, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644)
        try:
            os.write(fd, data)  # announced by publish() as one opaque whole-file write
        finally:
            os.close(fd)

    publish(path, write, expected_size=len(data))


def remove_partials(directory: Path) -> list[Path]:
    """Delete leftover ``*.partial`` files of interrupted publications; return what was removed."""
    removed = []
    if directory.is_dir():
        for entry in directory.iterdir():
            if entry.name.endswith(PARTIAL_SUFFIX):
                unlink(entry)
                removed.append(entry)
    return removed
