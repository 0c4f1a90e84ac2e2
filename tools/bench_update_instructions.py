#!/usr/bin/env python3
"""Instructions per ``SprintFilter.update`` at Fig. 4's setting, counted by valgrind (deterministic).

Usage::

    python tools/bench_update_instructions.py [--nodes 1000000] [--frames 2000]
                                              [--seq-len 100 1000 10000] [--json OUT.json]

Wall-clock time on a shared machine drifts by up to 2x within minutes; an instruction count
does not. For each sequence length the script runs itself twice under
``valgrind --tool=callgrind``: once driving ``--frames`` frames through the filter (one hit per
frame, the correct vertex, forward from vertex 12,345 as in ``tools/bench_fig4.py``; crossing
into the next sequence at a sequence end), once driving none, after the same set-up and 30
warm-up frames. The difference divided by ``--frames`` is the cost of one update (the same-run
baseline cancels start-up and set-up). Hash randomisation, the garbage collector and OpenBLAS'
worker threads (which spin for a varying while) are pinned or off, so two runs give the same
count. Prints a table; ``--json`` writes ``{"rows": [{"nodes", "seq_len", "frames",
"instructions_per_update"}]}``. Needs ``valgrind`` (Debian's package); about 1 minute per row.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

START = 12_345
WARMUP = 30


def drive(nodes: int, seq_len: int, frames: int) -> None:
    """The measured program: set-up, warm-up, then ``frames`` updates."""
    import numpy as np

    from sprint_map.hmm import HMMConfig, MemoryGraphSource, SprintFilter

    filt = SprintFilter(HMMConfig(), MemoryGraphSource([seq_len] * (nodes // seq_len)))
    ids = np.zeros(1, dtype=np.int64)
    dists = np.zeros(1, dtype=np.float32)
    for t in range(WARMUP):
        ids[0] = (START + t) % nodes
        filt.update(ids, dists)
    filt.reset()
    gc.disable()
    for t in range(frames):
        ids[0] = (START + t) % nodes
        filt.update(ids, dists)


def count(nodes: int, seq_len: int, frames: int) -> int:
    """Instructions valgrind counts for one run of :func:`drive`."""
    env = dict(os.environ, PYTHONHASHSEED="0", OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    out = subprocess.run(
        ["valgrind", "--tool=callgrind", "--callgrind-out-file=/dev/null", sys.executable,
         __file__, "--child", str(nodes), str(seq_len), str(frames)],
        env=env, capture_output=True, text=True, check=True)
    match = re.search(r"refs:\s+([\d,]+)", out.stderr)
    if match is None:
        raise RuntimeError(f"no instruction count in valgrind's output:\n{out.stderr[-2000:]}")
    return int(match.group(1).replace(",", ""))


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if args[:1] == ["--child"]:
        drive(*(int(a) for a in args[1:4]))
        return 0
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nodes", type=int, default=1_000_000)
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--seq-len", type=int, nargs="+", default=[100, 1000, 10_000])
    parser.add_argument("--json", type=Path)
    opts = parser.parse_args(args)
    rows: list[dict[str, Any]] = []
    print(f"{'nodes':>9} {'seq_len':>7} {'frames':>6} {'instructions/update':>20}")
    for seq_len in opts.seq_len:
        per = (count(opts.nodes, seq_len, opts.frames) - count(opts.nodes, seq_len, 0)) \
            / opts.frames
        rows.append({"nodes": opts.nodes, "seq_len": seq_len, "frames": opts.frames,
                     "instructions_per_update": round(per)})
        print(f"{opts.nodes:>9} {seq_len:>7} {opts.frames:>6} {per:>20,.0f}", flush=True)
    if opts.json:
        opts.json.write_text(json.dumps({"rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
