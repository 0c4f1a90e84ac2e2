"""Files the tool writes where the user asks (exports, traces, ``--out``): one way to write them.

Every such file goes through :class:`Output`, which is made *before* the work whose result it
holds, so a path that cannot be written is refused before anything is computed or committed:

* **where**: a symbolic link at the path is followed (as the shell's ``>`` does) and the file
  is written at its target; the target must not lie inside a map directory (``forbidden``:
  the map's own files are never an output) and its directory must exist;
* **what is there**: nothing or a regular file is replaced atomically (below); a FIFO or a
  character device (``/dev/stdout``, a pipe, a terminal, ``/proc/self/fd/1``), and any path
  under ``/dev`` or ``/proc``, is written in place, streamed, never replaced; a directory, a
  socket or a block device is refused (``InputError``);
* **atomically**: the data goes to a partial file of a name no other run uses
  (``OUT.<pid>-<random>.partial``), created with ``O_CREAT | O_EXCL | O_NOFOLLOW`` (a link
  planted at that name is never written through: the create fails), fsynced, then renamed over
  the target and the directory fsynced. Two runs to one path each publish a whole file, the
  last rename wins; a reader sees the old file or a whole new one. Partial files of runs that
  died (their pid is gone), and the legacy ``OUT.partial``, are removed by the next run;
* **several files as one unit** (:func:`commit_all`): every partial is written and fsynced
  before the first rename, so a full disk or an error leaves the old set whole.

Cost: O(1) system calls per file beyond the writes, plus one directory listing to find stale
partials.
"""

from __future__ import annotations

import contextlib
import os
import re
import stat
from collections.abc import Iterable, Sequence
from pathlib import Path
from types import TracebackType
from typing import IO

from sprint_map.errors import InputError, StorageIOError
from sprint_map.util import atomic

__all__ = ["Output", "commit_all", "inside"]

#: Paths written in place whatever they are (devices, ``/proc/self/fd/N``): never renamed over.
IN_PLACE_ROOTS = ("/dev", "/proc")


def inside(path: Path, root: str | os.PathLike[str]) -> bool:
    """Whether ``path`` (resolved) is ``root`` (resolved) or lies under it. O(depth)."""
    resolved_root = Path(os.path.realpath(root))
    return path == resolved_root or resolved_root in path.parents


class Output:
    """One file to write at ``path``, checked and opened now (see the module doc).

    Use as a context manager: on an exception the partial file is removed and the old file
    (if any) stays; :meth:`commit` publishes. ``stream`` is the binary stream to write.

    Raises
    ------
    InputError
        The path is a directory, a socket or a block device, its directory does not exist,
        it lies inside one of ``forbidden`` (map directories), or it cannot be created.
    """

    def __init__(self, path: str | os.PathLike[str], what: str, *,
                 forbidden: Sequence[str | os.PathLike[str]] = ()) -> None:
        self.asked = Path(path)
        self.what = what
        self.in_place = False
        try:
            st: os.stat_result | None = os.stat(self.asked)  # follows links
        except FileNotFoundError:
            st = None
        except OSError as exc:
            raise InputError(f"cannot write {self.asked}: {exc.strerror or exc}") from exc
        if st is not None and stat.S_ISDIR(st.st_mode):
            raise InputError(f"{self.asked} is a directory: give the {what} file to write")
        absolute = Path(os.path.abspath(self.asked))
        lexical_device = any(absolute == Path(r) or Path(r) in absolute.parents
                             for r in IN_PLACE_ROOTS)
        if st is not None and not stat.S_ISREG(st.st_mode):
            if not (stat.S_ISFIFO(st.st_mode) or stat.S_ISCHR(st.st_mode)):
                raise InputError(f"{self.asked} is a socket or a block device: cannot write the "
                                 f"{what} there")
            self.in_place = True
        elif lexical_device:
            self.in_place = True
        self.target = absolute if self.in_place else Path(os.path.realpath(self.asked))
        for root in forbidden:
            if inside(self.target, root):
                raise InputError(f"{self.asked} is inside the map {root}: write the {what} "
                                 "outside the map directory")
        if not self.target.parent.is_dir():
            raise InputError(f"{self.target.parent} is not a directory: cannot write "
                             f"{self.target.name}")
        self.partial: Path | None = None
        try:
            if self.in_place:
                flags = os.O_WRONLY | os.O_CLOEXEC | os.O_NOCTTY
                fd = os.open(self.asked, flags | (os.O_TRUNC if st is not None and
                                                  stat.S_ISREG(st.st_mode) else 0))
            else:
                remove_stale_partials(self.target)
                self.partial = self.target.with_name(
                    f"{self.target.name}.{os.getpid()}-{os.urandom(4).hex()}"
                    f"{atomic.PARTIAL_SUFFIX}")
                fd = os.open(self.partial, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW
                             | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            raise InputError(f"cannot write {self.asked}: {exc.strerror or exc}") from exc
        self.stream: IO[bytes] = os.fdopen(fd, "wb")
        self.done = False

    def __enter__(self) -> Output:
        return self

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        if not self.done:
            self.discard()
        if isinstance(exc, OSError):  # a write into the output failed (a full disk, ...)
            raise StorageIOError(f"cannot write {self.asked}: {exc.strerror or exc}") from exc

    def finish(self) -> None:
        """Flush and fsync the written data (a failure is final: ``StorageIOError``)."""
        try:
            self.stream.flush()
            if not self.in_place:
                atomic.fsync(self.stream.fileno(), self.partial or self.target)
        except OSError as exc:
            self.discard()
            raise StorageIOError(f"cannot write {self.asked}: {exc.strerror or exc}") from exc

    def publish(self) -> None:
        """Rename the finished partial over the target and make it durable."""
        try:
            self.stream.close()
            if self.partial is not None:
                atomic.replace(self.partial, self.target)
                self.partial = None
                atomic.fsync_dir(self.target.parent)
        except OSError as exc:
            self.discard()
            raise StorageIOError(f"cannot write {self.asked}: {exc.strerror or exc}") from exc
        self.done = True

    def commit(self) -> None:
        """:meth:`finish` then :meth:`publish`: the reader sees the whole new file."""
        self.finish()
        self.publish()

    def discard(self) -> None:
        """Close and remove the partial file: the old file (if any) is left as it was."""
        self.done = True
        with contextlib.suppress(OSError):
            self.stream.close()
        if self.partial is not None:
            with contextlib.suppress(OSError):
                os.unlink(self.partial)
            self.partial = None


def commit_all(outputs: Iterable[Output]) -> None:
    """Publish several outputs as one unit: all finished (fsynced) before the first rename,
    so a failure before that leaves every old file in place. O(files)."""
    todo = list(outputs)
    try:
        for out in todo:
            out.finish()
    except BaseException:
        for out in todo:
            out.discard()
        raise
    for out in todo:
        out.publish()


_PARTIAL_RE = re.compile(r"\.(\d+)-[0-9a-f]{8}" + re.escape(atomic.PARTIAL_SUFFIX) + "$")


def remove_stale_partials(target: Path) -> list[Path]:
    """Remove the partial files of ``target`` left by runs that died (their pid is gone) and
    the legacy ``target.partial``; links are removed, never followed. O(directory entries)."""
    removed: list[Path] = []
    prefix = target.name
    try:
        entries = list(os.scandir(target.parent))
    except OSError:
        return removed
    for entry in entries:
        if not entry.name.startswith(prefix):
            continue
        rest = entry.name[len(prefix):]
        match = _PARTIAL_RE.fullmatch(rest)
        legacy = rest == atomic.PARTIAL_SUFFIX
        if (match is None or _alive(int(match.group(1)))) and not legacy:
            continue
        if entry.is_dir(follow_symlinks=False):
            continue
        with contextlib.suppress(OSError):
            os.unlink(entry.path)
            removed.append(Path(entry.path))
    return removed


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
