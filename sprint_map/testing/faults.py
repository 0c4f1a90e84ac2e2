"""Fault injection and simulated power loss over the map's file seam (testing tools).

Every file-system call the map makes on its own files goes through :mod:`sprint_map.util.atomic`,
which calls a hook first (:func:`~sprint_map.util.atomic.set_file_hook`). The classes here are
such hooks; nothing in this module runs unless a test or a tool installs one with :func:`installed`.

- :class:`CallRecorder` lists the calls an operation makes: its failure surface.
- :class:`FaultInjector` fails the n-th call with an ``OSError`` (EIO, ENOSPC, ...), as the OS
  would; a failed write may leave a torn prefix behind, and ``sticky`` fails every later call too
  (a disk that died).
- :class:`PowerLossSimulator` tracks what each call made durable (a file's data at its fsync, a
  directory's entries at the directory's fsync), raises :class:`PowerCut` at a chosen call, and
  :meth:`PowerLossSimulator.apply` then rewrites the map's files into one state a disk could hold
  after losing power: each write not yet fsynced dropped, kept, or torn (a random prefix of the
  writes since the last fsync, the last one cut short or zero-filled), each entry not yet
  fsynced in its directory created/renamed/removed or not.

LMDB is not simulated: it does its own I/O, and a commit returns only once fsynced (the defaults
``sync=True, metasync=True``), so after a power cut LMDB holds exactly the commits that returned.
A process that dies at the cut also leaves LMDB exactly so: tests close the environment without
committing anything more.
"""

from __future__ import annotations

import errno as errno_codes
import os
import random
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sprint_map.util import atomic

__all__ = ["CallRecorder", "FaultInjector", "NOT_SIMULATED", "PowerCut", "PowerLossSimulator",
           "installed"]

#: Names in a map directory that the simulator leaves alone (LMDB does its own durability, the
#: writer lock holds no data).
NOT_SIMULATED = ("map.lmdb", "LOCK")


@contextmanager
def installed(hook: atomic.FileHook) -> Iterator[atomic.FileHook]:
    """Install ``hook`` on the file seam for the duration of the ``with`` block."""
    previous = atomic.set_file_hook(hook)
    try:
        yield hook
    finally:
        atomic.set_file_hook(previous)


@dataclass
class CallRecorder:
    """A hook that records every call as ``(op, path)``."""

    calls: list[tuple[str, Path]] = field(default_factory=list)

    def __call__(self, op: str, path: Path, info: dict[str, Any]) -> None:
        self.calls.append((op, path))


class FaultInjector:
    """A hook that fails the ``nth`` call among ``ops`` with ``OSError(error)``.

    Parameters
    ----------
    nth : int
        Which call fails (1-based, counting only calls whose op is in ``ops``).
    error : int
        The errno, e.g. ``errno.EIO`` or ``errno.ENOSPC``.
    ops : iterable of str
        The ops counted (default: all of :data:`~sprint_map.util.atomic.FILE_OPS`).
    sticky : bool
        Fail every call after the ``nth`` as well, whatever its op (a disk that died): the
        rollback's calls fail too.
    seed : int
        Seeds the length of the torn prefix a failed write leaves.
    """

    def __init__(self, nth: int, error: int = errno_codes.EIO, *,
                 ops: Iterable[str] = atomic.FILE_OPS, sticky: bool = False,
                 seed: int = 0) -> None:
        self.nth = nth
        self.error = error
        self.ops = frozenset(ops)
        self.sticky = sticky
        self.rng = random.Random(seed)
        self.calls = 0
        #: Every call made, as ``(op, path, failed)``.
        self.log: list[tuple[str, Path, bool]] = []

    @property
    def failed(self) -> list[tuple[str, Path]]:
        return [(op, path) for op, path, failed in self.log if failed]

    def __call__(self, op: str, path: Path, info: dict[str, Any]) -> None:
        fail = self.sticky and self.calls >= self.nth
        if op in self.ops:
            self.calls += 1
            fail = fail or self.calls == self.nth
        self.log.append((op, path, fail))
        if not fail:
            return
        if op == "write":
            self._tear(path, info)
        raise OSError(self.error, f"{os.strerror(self.error)} (injected)", str(path))

    def _tear(self, path: Path, info: dict[str, Any]) -> None:
        """Leave what a write that fails half-way leaves: a prefix of its data."""
        data = info.get("data")
        if data is None:  # an opaque writer (FAISS) had started the file
            path.write_bytes(os.urandom(self.rng.randint(0, 64)))
        elif len(data) > 1:
            os.pwrite(info["fd"], data[: self.rng.randint(1, len(data) - 1)], info["offset"])


class PowerCut(BaseException):
    """The simulated power cut: a ``BaseException``, so no error handler of the code treats it
    as an error to recover from; the process is "dead" from this call on."""


@dataclass
class _Inode:
    durable: bytes  # the data as of the file's last fsync (b"" for a file never fsynced)
    pending: list[tuple[Any, ...]] = field(default_factory=list)  # writes since then


class PowerLossSimulator:
    """A hook that tracks durability of the map's files and cuts the power at a chosen call.

    Parameters
    ----------
    root : Path
        The map directory (its files must be at rest when the simulator is created: all durable).
    cut_at : int, optional
        The call (1-based, every op counts) at which :class:`PowerCut` is raised instead of
        making the call; every later call raises it too. None: never (only count).
    seed : int
        Seeds every choice :meth:`apply` makes.

    Notes
    -----
    Keeps a copy of every file of the map (but LMDB's) in memory: for small test maps.
    """

    def __init__(self, root: Path, *, cut_at: int | None = None, seed: int = 0) -> None:
        self.root = Path(root).resolve()
        self.cut_at = cut_at
        self.calls = 0
        self.cut = False
        self.rng = random.Random(seed)
        self._inodes: list[_Inode] = []
        self._names: dict[Path, dict[str, int]] = {}
        self._durable_names: dict[Path, dict[str, int]] = {}
        for directory in [self.root, *sorted(p for p in self.root.iterdir() if p.is_dir())]:
            if directory.name in NOT_SIMULATED:
                continue
            self._names[directory] = {
                entry.name: self._new(entry.read_bytes())
                for entry in sorted(directory.iterdir())
                if entry.is_file() and entry.name not in NOT_SIMULATED
            }
            self._durable_names[directory] = dict(self._names[directory])

    def _new(self, durable: bytes) -> int:
        self._inodes.append(_Inode(durable))
        return len(self._inodes) - 1

    # --- the hook ---------------------------------------------------------------------------
    def __call__(self, op: str, path: Path, info: dict[str, Any]) -> None:
        if self.cut:
            raise PowerCut("the power is off")
        self.calls += 1
        if self.calls == self.cut_at:
            self.cut = True
            raise PowerCut(f"power cut at call {self.calls} ({op} {path.name})")
        path = path.resolve()
        if op == "fsync_dir":
            if path in self._names:
                self._reconcile(path)
                self._durable_names[path] = dict(self._names[path])
            return
        names = self._names.get(path.parent)
        if names is None:
            return  # not a file of this map
        if op == "create":
            names[path.name] = self._new(b"")
            return
        if op == "unlink":
            names.pop(path.name, None)
            return
        if op == "replace":
            dst = Path(info["dst"]).resolve()
            self._names[dst.parent][dst.name] = names.pop(path.name)
            return
        if path.name not in names:  # created behind the seam's back
            names[path.name] = self._new(b"")
        inode = self._inodes[names[path.name]]
        if op == "fsync":
            inode.durable, inode.pending = path.read_bytes(), []
        elif op == "truncate":
            inode.pending.append(("truncate", info["size"]))
        elif op == "write" and info["data"] is None:
            inode.pending = [("opaque",)]  # a whole-file writer: only its result is known
        elif op == "write":
            inode.pending.append(("write", info["offset"], bytes(info["data"])))

    def _reconcile(self, directory: Path) -> None:
        """Account for entries changed without a call through the seam (e.g. ``Path.unlink``)."""
        names = self._names[directory]
        present = {e.name for e in directory.iterdir()
                   if e.is_file() and e.name not in NOT_SIMULATED}
        for name in set(names) - present:
            del names[name]
        for name in present - set(names):
            ino = self._new(b"")
            self._inodes[ino].pending = [("opaque",)]
            names[name] = ino

    # --- after the cut ----------------------------------------------------------------------
    def apply(self) -> list[str]:
        """Rewrite the map's files into a state the disk may hold after the cut.

        Call it once the code under test has stopped (the :class:`PowerCut` propagated and the
        store was abandoned without closing it cleanly). Returns what differs from the files as
        the dead process left them, one line per file.
        """
        self.cut = True
        changes = []
        for directory, names in self._names.items():
            self._reconcile(directory)
            real = {ino: (directory / name).read_bytes() for name, ino in names.items()}
            durable = self._durable_names[directory]
            outcome: dict[str, bytes] = {}
            for name in sorted(set(names) | set(durable)):
                now, then = names.get(name), durable.get(name)
                # An entry whose change is not yet durable in its directory: either state.
                ino = now if now == then else self.rng.choice([now, then])
                if ino is not None:
                    outcome[name] = self._content(self._inodes[ino], real.get(ino))
                if ino != now:
                    changes.append(f"{name}: {'dropped' if ino is None else 'entry undone'}")
                elif ino is not None and outcome[name] != real.get(ino):
                    changes.append(f"{name}: {len(real[ino])} -> {len(outcome[name])} bytes")
            for name in names:
                (directory / name).unlink()
            for name, data in outcome.items():
                (directory / name).write_bytes(data)
        return changes

    def _content(self, inode: _Inode, real: bytes | None) -> bytes:
        """The data of a file after the cut: durable data plus some of the writes since."""
        if not inode.pending:
            return inode.durable
        fate = self.rng.choice(("drop", "keep", "tear", "zero"))
        if inode.pending == [("opaque",)]:
            if real is None or fate == "drop":
                return inode.durable
            if fate == "keep":
                return real
            cut = self.rng.randint(0, len(real))
            return real[:cut] if fate == "tear" else real[:cut] + bytes(len(real) - cut)
        data = bytearray(inode.durable)
        if fate == "drop":
            return bytes(data)
        ops = inode.pending
        applied = len(ops) if fate == "keep" else self.rng.randint(0, len(ops) - 1)
        for op in ops[:applied]:
            _apply(data, op)
        if applied < len(ops):
            op = ops[applied]
            if op[0] == "write" and fate == "tear":
                _apply(data, ("write", op[1], op[2][: self.rng.randint(0, len(op[2]))]))
            elif op[0] == "write":  # the size reached the disk, the data did not
                _apply(data, ("write", op[1], bytes(len(op[2]))))
        return bytes(data)


def _apply(data: bytearray, op: tuple[Any, ...]) -> None:
    if op[0] == "truncate":
        del data[op[1]:]
        data.extend(bytes(op[1] - len(data)))
    else:
        _, offset, chunk = op
        if len(data) < offset:
            data.extend(bytes(offset - len(data)))
        data[offset : offset + len(chunk)] = chunk
