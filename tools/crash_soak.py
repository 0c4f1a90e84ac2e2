#!/usr/bin/env python3
"""Crash soak: SIGKILL map writers at random instants thousands of times; count violations.

Usage::

    python tools/crash_soak.py --kills 1000 [--json OUT] [--seed 1] [--kills-per-map 25]
                               [--max-wait 0.04] [--workdir DIR]

The random-kill loop of ``tests/storage/test_crash.py`` (``kill_loop`` in ``tests/helpers/crash_worker.py``),
at soak size. Writers are forked from a warmed-up zygote process; each opens a map and adds a
deterministic stream of sequences (one-shot and streamed adds, and groups of three committed
in one transaction as ``ingest A B C --no-merge`` does, with edges that merge components) and is killed after a random delay (some during open and recovery). After every
kill the map is opened read-only and must hold every acknowledged sequence bit for bit, whole
sequences only, the components of its edges and pass ``check`` (but for a partial index
file); then a writable open or ``check --repair`` (alternately) must leave it passing ``check``
strictly, the repair finding nothing but files past the commit. Every ``--kills-per-map`` kills
a writer runs to completion, the map is verified and searched, and a fresh map starts.

A violation does not stop the soak: it is recorded and that map abandoned. Prints progress and
a summary; ``--json`` also writes it (``kills``, ``violations`` (a list: must be empty),
``sequences_verified``, ...). Exits 1 if there was any violation.
"""

from __future__ import annotations

import argparse
import importlib
import json
import shutil
import sys
import tempfile
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]


def load_worker() -> ModuleType:
    """The crash harness, ``tests.helpers.crash_worker`` (it lives with the tests it serves;
    a script's path starts at ``tools/``, so the checkout's root is put first)."""
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    return importlib.import_module("tests.helpers.crash_worker")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kills", type=int, default=1000, help="SIGKILLs in all (default 1000)")
    parser.add_argument("--json", type=Path, help="also write the summary as JSON here")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--kills-per-map", type=int, default=25,
                        help="kills before a writer runs to completion and a new map starts")
    parser.add_argument("--max-wait", type=float, default=0.04,
                        help="longest a writer runs before its kill, in seconds")
    parser.add_argument("--workdir", type=Path, help="parent of the scratch dir (default /tmp)")
    args = parser.parse_args(argv)

    worker = load_worker()
    scratch = Path(tempfile.mkdtemp(prefix="crash-soak-", dir=args.workdir))
    zygote = worker.Zygote(scratch / "zygote.log")

    def progress(stats: object) -> None:
        d = stats.to_dict()  # type: ignore[attr-defined]
        print(f"kills {d['kills']:>6}  maps {d['maps']:>4}  sequences verified "
              f"{d['sequences_verified']:>8}  violations {len(d['violations'])}  "
              f"{d['seconds']:.0f} s", file=sys.stderr, flush=True)

    try:
        stats = worker.kill_loop(scratch, zygote, args.kills, args.seed,
                                 kills_per_map=args.kills_per_map, max_wait=args.max_wait,
                                 keep_going=True, progress=progress)
    finally:
        zygote.close()
        shutil.rmtree(scratch, ignore_errors=True)
    given = sys.argv[1:] if argv is None else argv
    summary = {"command": " ".join(["python", "tools/crash_soak.py", *given]),
               **stats.to_dict()}
    width = max(len(k) for k in summary)
    for key, value in summary.items():
        shown = len(value) if key == "violations" else value
        print(f"{key:<{width}}  {shown}")
    for violation in stats.violations:
        print(f"violation: {violation}")
    if args.json:
        args.json.write_text(json.dumps(summary, indent=2) + "\n")
    return 1 if stats.violations else 0


if __name__ == "__main__":
    sys.exit(main())
