"""Durable file primitives: fsync'd appends and atomic publication of whole files.

A failed fsync fails the operation and is never retried: after a failed fsync the kernel may have
marked the dirty pages clean, so a retry could report success for lost data ("fsyncgate").
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sprint_map.errors import StorageIOError

PARTIAL_SUFFIX = ".partial"


def fsync_dir(path: Path) -> None:
    """Make a directory's entries (created, renamed, removed files) durable."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def publish(path: Path, write: Callable[[Path], Any]) -> None:
    """Write ``path`` atomically: ``write(partial)``, fsync, ``os.replace``, fsync the directory.

    ``write`` receives the temporary path and must create the file there. Readers see either the
    old file or the complete new one, never a torn one.
    """
    partial = path.with_name(path.name + PARTIAL_SUFFIX)
    try:
        write(partial)
        fd = os.open(partial, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(partial, path)
        fsync_dir(path.parent)
    except OSError as exc:
        partial.unlink(missing_ok=True)
        raise StorageIOError(f"cannot write {path}: {exc.strerror or exc}") from exc


def remove_partials(directory: Path) -> list[Path]:
    """Delete leftover ``*.partial`` files of interrupted publications; return what was removed."""
    removed = []
    if directory.is_dir():
        for entry in directory.iterdir():
            if entry.name.endswith(PARTIAL_SUFFIX):
                entry.unlink(missing_ok=True)
                removed.append(entry)
    return removed
