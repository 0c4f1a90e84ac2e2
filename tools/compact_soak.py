#!/usr/bin/env python3
"""Compaction soak: SIGKILL ``compact`` at random instants thousands of times; count violations.

Usage::

    python tools/compact_soak.py --kills 1000 [--json OUT] [--seed 1] [--kills-per-map 30]
                                 [--max-wait S] [--workdir DIR]

The random-kill loop of ``tests/storage/test_crash.py::test_random_kills_during_compaction``
(``compact_kill_loop`` in ``tests/helpers/crash_worker.py``) at soak size: maps of six sequences with
two removed; a compaction forked from a warmed-up zygote is killed a random delay after it is
ready. After every kill the map must pass ``check`` and mean exactly what it meant before
(every live sequence bit for bit, the removed ones absent, the components of the edges),
whichever generation is selected; every other kill a writer's open must leave it strictly
clean. Prints the counts (kills landing before and after the switch) and exits 1 on any
violation.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

from crash_soak import load_worker  # the sibling script: how tools reach the crash harness


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kills", type=int, default=1000)
    parser.add_argument("--json", type=Path, help="also write the summary as JSON here")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--kills-per-map", type=int, default=30)
    parser.add_argument("--max-wait", type=float, default=None,
                        help="longest a compaction runs before its kill, in seconds (default: "
                        "1.2 x a compaction of the same map run to completion)")
    parser.add_argument("--workdir", type=Path, help="parent of the scratch dir (default /tmp)")
    args = parser.parse_args(argv)

    worker = load_worker()
    scratch = Path(tempfile.mkdtemp(prefix="compact-soak-", dir=args.workdir))
    zygote = worker.Zygote(scratch / "zygote.log")

    def progress(stats: object) -> None:
        d = stats.to_dict()  # type: ignore[attr-defined]
        print(f"kills {d['kills']:>6}  old {d['old_map_after_kill']:>6}  new "
              f"{d['new_map_after_kill']:>6}  violations {len(d['violations'])}  "
              f"{d['seconds']:.0f} s", file=sys.stderr, flush=True)

    try:
        stats = worker.compact_kill_loop(scratch, zygote, args.kills, args.seed,
                                         kills_per_map=args.kills_per_map,
                                         max_wait=args.max_wait, keep_going=True,
                                         progress=progress)
    finally:
        zygote.close()
        shutil.rmtree(scratch, ignore_errors=True)
    given = sys.argv[1:] if argv is None else argv
    summary = {"command": " ".join(["python", "tools/compact_soak.py", *given]),
               **stats.to_dict()}
    for key, value in summary.items():
        print(f"{key:<22}  {len(value) if key == 'violations' else value}")
    for violation in stats.violations:
        print(f"VIOLATION {violation}")
    if args.json:
        args.json.write_text(json.dumps(summary, indent=2))
    return 1 if stats.violations else 0


if __name__ == "__main__":
    sys.exit(main())
