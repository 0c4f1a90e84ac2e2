"""Generations of a map directory: which copy of the data is live, and who still reads an old one.

Compaction (:mod:`sprint_map.storage.compaction`) cannot rewrite the map in place: it renumbers
every vertex and shrinks LMDB by copying it. So it builds a complete new copy of the data (LMDB,
shards, index) in a *generation directory* ``MAP/gen-NNNNNN/`` and then selects it with one
atomic step: publishing the small file ``MAP/CURRENT`` that names it (``*.partial``, fsync,
``os.replace``, fsync the directory). Without ``CURRENT`` the data lives at the top of the map
directory (generation 0: ``map.lmdb/``, ``shards/``, ``index/``), which is the layout every map
has until its first compaction.

A directory that ``CURRENT`` does not select is garbage: a compaction's staging area (killed
before publishing) or the previous generation (after publishing). It is removed by the
compaction itself or by the next writer's open, unless a reader still has it open.

**Reader pins.** Every open of a map (reader or writer) holds a shared ``flock`` on the
``data.mdb`` of the generation it opened, for as long as it stays open. A generation is removed
only under an exclusive, non-blocking ``flock`` on that file, so a reader opened before a
compaction keeps a consistent view of the old generation (its LMDB snapshots, shard files and
index files all stay) until it closes; the old generation's space is reclaimed by the next
writer's open after that. LMDB itself never ``flock``s ``data.mdb`` (it locks ``lock.mdb`` with
``fcntl``), so the pins do not interfere with it.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import re
import time
from pathlib import Path

from sprint_map.errors import MapCorruptError, NotAMapError
from sprint_map.testing.crash import crash_point
from sprint_map.util import atomic

__all__ = ["CURRENT_NAME", "GEN_PARTS", "GEN_RE", "PIN_ATTEMPTS", "PIN_FILE", "current_data",
           "gen_name", "gen_number", "pin_current", "pin_path", "publish_current",
           "remove_generation", "stale_generations", "unpin"]

CURRENT_NAME = "CURRENT"
GEN_RE = re.compile(r"^gen-(\d{6})$")
#: What a generation holds; generation 0 holds them at the top of the map directory.
GEN_PARTS = ("shards", "index", "map.lmdb")  # map.lmdb last: its data.mdb is the pin
PIN_FILE = ("map.lmdb", "data.mdb")
#: Attempts to pin the current generation while a compaction switches it (each ~1 ms).
PIN_ATTEMPTS = 2000


def gen_name(number: int) -> str:
    return f"gen-{number:06d}"


def gen_number(root: Path, data: Path) -> int:
    """Generation number of the data directory ``data`` of the map at ``root`` (0: the top)."""
    if data == root:
        return 0
    match = GEN_RE.match(data.name)
    if match is None:
        raise MapCorruptError(f"{data} is not a generation directory of {root}")
    return int(match.group(1))


def current_data(root: Path) -> Path:
    """The live data directory of the map at ``root``: ``root`` itself or ``root/gen-N``.

    Raises
    ------
    MapCorruptError
        If ``CURRENT`` names something that is not a generation directory.
    """
    try:
        raw = (root / CURRENT_NAME).read_bytes()
    except FileNotFoundError:
        return root
    except NotADirectoryError:
        raise NotAMapError(f"not a sprint-map directory: {root}") from None
    except IsADirectoryError:
        raise MapCorruptError(f"{root / CURRENT_NAME} is a directory, not the file naming the "
                              "live generation") from None
    try:
        name = raw.decode("ascii").strip()
    except UnicodeDecodeError:
        raise MapCorruptError(f"{root / CURRENT_NAME} is corrupt: it does not name a generation "
                              "directory") from None
    if not GEN_RE.match(name) or not (root / name).is_dir():
        raise MapCorruptError(f"{root / CURRENT_NAME} names {name!r}, which is not a generation "
                              "directory of the map")
    return root / name


def pin_path(data: Path) -> Path:
    return data.joinpath(*PIN_FILE)


def pin_current(root: Path) -> tuple[Path, int | None]:
    """Resolve the live generation and pin it (shared ``flock``); return ``(data dir, fd)``.

    The fd is None when the generation has no ``data.mdb`` (then the map is not a map, and the
    caller's open fails). ``CURRENT`` is read again once the pin is held: a compaction that
    switched generations meanwhile makes this retry on the new one, so the pinned generation is
    the live one at the moment it was pinned.

    Notes
    -----
    O(1): one read of ``CURRENT``, one ``open`` and one ``flock``, a few more only while a
    compaction is removing the generation being pinned.
    """
    for _ in range(PIN_ATTEMPTS):
        data = current_data(root)
        try:
            fd = os.open(pin_path(data), os.O_RDONLY)
        except FileNotFoundError:
            if current_data(root) == data:
                return data, None
            continue  # switched and removed between the two looks: try the new one
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:  # being removed right now, under the exclusive lock
            os.close(fd)
            time.sleep(0.001)
            continue
        if current_data(root) == data:
            return data, fd
        os.close(fd)
    raise MapCorruptError(f"could not pin the live generation of {root} (it kept changing)")


def unpin(fd: int | None) -> None:
    if fd is not None:
        os.close(fd)  # drops the shared flock


def stale_generations(root: Path, data: Path) -> list[Path]:
    """Data directories of ``root`` other than the live ``data``: old generations, staging.

    Generation 0 (the top level) is listed as ``root`` when a generation directory is live and
    any of its parts is still there.
    """
    stale = []
    if data != root and any((root / part).exists() for part in GEN_PARTS):
        stale.append(root)
    if root.is_dir():
        for entry in sorted(root.iterdir()):
            if GEN_RE.match(entry.name) and entry != data and entry.is_dir():
                stale.append(entry)
    return stale


def remove_generation(root: Path, data: Path) -> bool:
    """Delete the (not live) generation ``data`` unless a process has it open; True if gone.

    Takes the exclusive ``flock`` on its ``data.mdb`` (non-blocking: a reader's shared pin makes
    this return False at once and leave everything in place). The parts go in the order of
    :data:`GEN_PARTS`, the pinned file last, so a kill part-way leaves a generation the next
    writer's open finishes removing.

    Notes
    -----
    O(files in the generation) unlinks (shards, index files, LMDB's two files).
    """
    fd = None
    # No data.mdb: a staging directory killed before its LMDB existed, or half removed already.
    with contextlib.suppress(FileNotFoundError, NotADirectoryError):
        fd = os.open(pin_path(data), os.O_RDONLY)
    try:
        if fd is not None:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                return False
        parts = [data / p for p in GEN_PARTS] if data == root else [data]
        for i, part in enumerate(parts):
            if i:
                crash_point("compact.old_partly_removed")  # also reached by a writer's open
            if part.is_dir():
                atomic.remove_tree(part)
            elif part.exists():
                atomic.unlink(part)
        atomic.fsync_dir(root)
        return True
    finally:
        if fd is not None:
            os.close(fd)


def publish_current(root: Path, data: Path) -> None:
    """Select generation ``data`` atomically: the commit point of a compaction."""
    atomic.publish_bytes(root / CURRENT_NAME, f"{data.name}\n".encode())
