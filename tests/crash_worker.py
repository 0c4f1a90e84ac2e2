"""Subprocess helper of the crash, lock and concurrency tests (run as a script, never imported
by pytest as a test module).

Modes::

    crash_worker.py write MAP --seed S [--count N] [--length L]
        Open MAP for writing, print ``ready``, and add sequences ``n, n+1, ...`` (``n`` =
        sequences already there) whose content is a pure function of (seed, index): see
        :func:`planned_sequence`. After each add returns, print ``ack <i>`` (flushed). Run it
        with ``SPRINT_MAP_CRASH_AT=<point>`` to have it SIGKILL itself at that crash point.
    crash_worker.py hold MAP
        Open MAP for writing, print ``locked``, then wait for stdin to close.
    crash_worker.py try-open MAP
        Try to open MAP for writing; print JSON ``{"error", "message", "seconds"}``.
    crash_worker.py zygote
        A fork server: imports everything once, then for each JSON line on stdin
        ``{"op": "spawn", ...write options..., "ack": FILE}`` forks a ``write`` child that appends
        ``ready`` and ``ack <i>`` lines to FILE (``os.write``: in the kernel once it returns) and
        replies ``{"pid": ...}``; ``{"op": "wait", "pid": P}`` reaps it and replies
        ``{"signal": ..., "code": ...}``. Forking a warmed-up process makes a kill-and-restart
        cycle cost milliseconds instead of a Python start-up (~0.7 s with numpy/faiss/cv2).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import traceback
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sprint_map.errors import SprintMapError
from sprint_map.storage.store import EdgeSpec, MapStore

WORKER = Path(__file__).resolve()
MAX_LENGTH = 90


def _rng(seed: int, index: int, what: str) -> np.random.Generator:
    return np.random.default_rng([seed, index, zlib.crc32(what.encode())])


def planned_length(seed: int, index: int, fixed: int | None = None) -> int:
    """Frames of sequence ``index``: ``fixed`` or a deterministic draw in 1..MAX_LENGTH."""
    return fixed if fixed else int(_rng(seed, index, "length").integers(1, MAX_LENGTH + 1))


@dataclass(frozen=True)
class Planned:
    """The deterministic content of the ``index``-th sequence a worker adds."""

    name: str
    descriptors: np.ndarray
    positions: np.ndarray | None
    edges: tuple[EdgeSpec, ...]


def planned_sequence(seed: int, index: int, dim: int, fixed_length: int | None = None) -> Planned:
    """Sequence ``index`` of the worker stream ``seed`` (same on every call, in every process).

    Every other sequence has positions; each has 0-2 edges to earlier sequences of the stream
    (so the i-th sequence of the stream must be seq id i, which holds when only the worker
    writes the map).
    """
    length = planned_length(seed, index, fixed_length)
    rng = _rng(seed, index, "content")
    descriptors = rng.standard_normal((length, dim)).astype(np.float32)
    positions = rng.uniform(-500, 500, (length, 3)) if index % 2 == 0 else None
    edges = []
    for _ in range(int(rng.integers(0, 3)) if index else 0):
        other = int(rng.integers(index))
        old_end = (other, int(rng.integers(planned_length(seed, other, fixed_length))))
        new_end = (None, int(rng.integers(length)))
        src, dst = (new_end, old_end) if rng.random() < 0.5 else (old_end, new_end)
        edges.append(EdgeSpec(src, dst, weight=float(rng.random()), frame=new_end[1]))
    return Planned(f"w-{index}", descriptors, positions, tuple(edges))


def add_planned(store: MapStore, seed: int, index: int, length: int | None = None) -> None:
    """Add sequence ``index`` of stream ``seed`` to ``store`` (it must be the next seq id)."""
    plan = planned_sequence(seed, index, store.config.dim, length)
    result = store.add_sequence(plan.descriptors, name=plan.name, positions=plan.positions,
                                edges=plan.edges)
    assert result.sequence.seq_id == index


def write(path: str, seed: int, count: int | None, length: int | None,
          emit: Callable[[str], None]) -> None:
    """Add planned sequences to the map at ``path``, acknowledging each with ``emit``."""
    with MapStore.open(path) as store:
        emit("ready")
        start = store.stats()["sequences"]
        index = start
        while count is None or index < start + count:
            add_planned(store, seed, index, length)
            emit(f"ack {index}")
            index += 1
    emit("done")


def _stdout_emit(line: str) -> None:
    print(line, flush=True)


def _zygote() -> None:
    for raw in sys.stdin:
        request = json.loads(raw)
        if request["op"] == "spawn":
            sys.stdout.flush()
            pid = os.fork()
            if pid == 0:  # child: never returns into the zygote loop
                status = 0
                try:
                    fd = os.open(request["ack"], os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)

                    def emit(line: str, fd: int = fd) -> None:
                        os.write(fd, f"{line}\n".encode())

                    write(request["map"], request["seed"], request.get("count"),
                          request.get("length"), emit)
                except BaseException:
                    traceback.print_exc()
                    status = 1
                os._exit(status)
            reply: dict[str, object] = {"pid": pid}
        elif request["op"] == "wait":
            _, status = os.waitpid(request["pid"], 0)
            reply = {
                "signal": os.WTERMSIG(status) if os.WIFSIGNALED(status) else None,
                "code": os.WEXITSTATUS(status) if os.WIFEXITED(status) else None,
            }
        else:
            raise ValueError(f"unknown op {request['op']!r}")
        print(json.dumps(reply), flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="mode", required=True)
    w = sub.add_parser("write")
    w.add_argument("map")
    w.add_argument("--seed", type=int, required=True)
    w.add_argument("--count", type=int)
    w.add_argument("--length", type=int)
    sub.add_parser("hold").add_argument("map")
    sub.add_parser("try-open").add_argument("map")
    sub.add_parser("zygote")
    args = parser.parse_args(argv)

    if args.mode == "write":
        write(args.map, args.seed, args.count, args.length, _stdout_emit)
    elif args.mode == "hold":
        with MapStore.open(args.map):
            _stdout_emit("locked")
            sys.stdin.read()
    elif args.mode == "try-open":
        start = time.monotonic()
        try:
            MapStore.open(args.map).close()
            result = {"error": None, "message": ""}
        except SprintMapError as exc:
            result = {"error": type(exc).__name__, "message": str(exc)}
        result["seconds"] = time.monotonic() - start
        print(json.dumps(result), flush=True)
    else:
        _zygote()
    return 0


if __name__ == "__main__":
    sys.exit(main())
