#!/usr/bin/env python3
"""The SPRINT paper's Fig. 4 simulation: time per HMM update, full graph versus subgraphs.

Usage::

    python tools/bench_fig4.py --json OUT.json --png OUT.png [--quick]
                               [--runs 10] [--steps 200] [--max-nodes 1000000]

For every total node count (100, 1k, 10k, 100k, 1M) and sequence length (100, 1k, 10k; not
longer than the map) the map is that many nodes split into equal sequences without edges. A
query drives forward one vertex per frame from a random start (crossing into the next sequence
at a sequence end) and the retrieval returns only the correct vertex (``k = 1``), as in the
paper. Each configuration is run ``--runs`` times, ``--steps`` frames each, every run starting
from a reset filter (after 10 untimed warm-up frames elsewhere), so the times include the first
frame's initialisation and the activation of every sequence the query enters. Both filters run the identical model with the default
:class:`~sprint_map.hmm.HMMConfig`:

* ``full_ms``: :class:`~sprint_map.hmm.FullGraphFilter`, one scipy CSR matrix over all nodes;
* ``sprint_ms``: :class:`~sprint_map.hmm.SprintFilter` over a
  :class:`~sprint_map.hmm.MemoryGraphSource` with its LRU component cache.

The timed call is ``update`` (the inference step the paper times); ``*_step_ms`` columns also
time ``step`` (update + decision) over a quarter of the frames. The two filters alternate run
by run, so that drift in the machine's speed does not enter the ratio; rows give the mean over
runs (as the paper) and the median (robust to load from other processes). The garbage collector is off while timing (as
``timeit`` does); both filters are single-threaded. Prints a table; ``--json`` writes ``{"rows": [{"nodes",
"seq_len", "full_ms", "sprint_ms", ...}]}``; ``--png`` a log-log plot. ``--quick`` runs 3 runs
of 50 frames up to 100k nodes.
"""

from __future__ import annotations

import argparse
import gc
import json
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map.hmm import FullGraphFilter, HMMConfig, MemoryGraphSource, SprintFilter

NODES = (100, 1_000, 10_000, 100_000, 1_000_000)
SEQ_LENS = (100, 1_000, 10_000)
WARMUP = 10


def time_run(filt: Any, start: int, steps: int, n_nodes: int, *, decide: bool) -> float:
    """Seconds per frame of one run: reset, then ``steps`` frames from vertex ``start``.

    An untimed warm-up of WARMUP frames elsewhere in the map precedes the run, so that each run
    starts with warm CPU caches whatever ran before it.
    """
    ids = np.zeros(1, dtype=np.int64)
    dists = np.zeros(1, dtype=np.float32)
    call = filt.step if decide else filt.update
    filt.reset()
    for t in range(WARMUP):
        ids[0] = (start + n_nodes // 2 + t) % n_nodes
        call(ids, dists)
    filt.reset()
    gc.disable()
    try:
        t0 = time.perf_counter()
        for t in range(steps):
            ids[0] = (start + t) % n_nodes
            call(ids, dists)
        elapsed = time.perf_counter() - t0
    finally:
        gc.enable()
    return elapsed / steps


def bench(nodes: tuple[int, ...], seq_lens: tuple[int, ...], runs: int, steps: int,
          seed: int = 0) -> list[dict[str, Any]]:
    """Run every (nodes, seq_len) configuration; return the result rows.

    The two filters alternate run by run (both see the same machine); each row reports the
    mean over runs (as the paper) and the median (robust to load from other processes).
    """
    rng = np.random.default_rng(seed)
    config = HMMConfig()
    rows: list[dict[str, Any]] = []
    for n in nodes:
        for seq_len in seq_lens:
            if seq_len > n:
                continue
            source = MemoryGraphSource([seq_len] * (n // seq_len))
            full = FullGraphFilter(config, source)
            sprint = SprintFilter(config, source)
            starts = rng.integers(0, n, size=runs).tolist()
            step_frames = max(steps // 4, 1)
            times: dict[str, list[float]] = {"full": [], "sprint": [], "full_step": [],
                                             "sprint_step": []}
            active: list[int] = []
            # The two filters alternate run by run, so that both see the same machine: on a
            # shared machine the speed drifts by up to 2x within minutes, and blocks of runs
            # would turn that drift into the ratio. (Each run's untimed warm-up frames re-warm
            # the CPU caches after the other filter's run: at 1M nodes the full graph streams
            # ~100 MB per frame through them.)
            for start in starts:
                times["sprint"].append(time_run(sprint, start, steps, n, decide=False))
                active.append(sprint.n_active_vertices)
                times["full"].append(time_run(full, start, steps, n, decide=False))
            for start in starts:
                times["sprint_step"].append(time_run(sprint, start, step_frames, n, decide=True))
                times["full_step"].append(time_run(full, start, step_frames, n, decide=True))
            ms = {k: 1e3 * statistics.mean(v) for k, v in times.items()}
            med = {k: 1e3 * statistics.median(v) for k, v in times.items()}
            row = {
                "nodes": n, "seq_len": seq_len,
                "full_ms": ms["full"], "sprint_ms": ms["sprint"],
                "speedup": ms["full"] / ms["sprint"],
                "full_median_ms": med["full"], "sprint_median_ms": med["sprint"],
                "median_speedup": med["full"] / med["sprint"],
                "full_step_ms": ms["full_step"], "sprint_step_ms": ms["sprint_step"],
                "step_speedup": ms["full_step"] / ms["sprint_step"],
                "sprint_active_vertices": statistics.mean(active), "runs": runs, "steps": steps,
            }
            rows.append(row)
            print(format_row(row), flush=True)
            del full, sprint, source
    return rows


HEADER = (f"{'nodes':>9} {'seq_len':>7} {'full ms':>9} {'sprint ms':>10} {'speedup':>8} "
          f"{'(median)':>9} {'full+dec ms':>11} {'sprint+dec ms':>13} {'speedup':>8} "
          f"{'active':>7}")


def format_row(row: dict[str, Any]) -> str:
    """One line of the printed table."""
    return (f"{row['nodes']:>9} {row['seq_len']:>7} {row['full_ms']:>9.4f} "
            f"{row['sprint_ms']:>10.4f} {row['speedup']:>7.0f}x {row['median_speedup']:>8.0f}x "
            f"{row['full_step_ms']:>11.4f} {row['sprint_step_ms']:>13.4f} "
            f"{row['step_speedup']:>7.0f}x {row['sprint_active_vertices']:>7.0f}")


def plot(rows: list[dict[str, Any]], path: Path) -> None:
    """Log-log plot of time per update versus nodes (the paper's Fig. 4)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 5))
    seq_lens = sorted({r["seq_len"] for r in rows})
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    full_by_n: dict[int, list[float]] = {}
    for r in rows:
        full_by_n.setdefault(r["nodes"], []).append(r["full_ms"])
    xs = sorted(full_by_n)
    ax.plot(xs, [statistics.mean(full_by_n[x]) for x in xs], "k-o", label="full graph")
    for i, seq_len in enumerate(seq_lens):
        sel = sorted((r for r in rows if r["seq_len"] == seq_len), key=lambda r: r["nodes"])
        ax.plot([r["nodes"] for r in sel], [r["sprint_ms"] for r in sel], "-s",
                color=colors[i % len(colors)], label=f"SPRINT, sequences of {seq_len}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("nodes in the map")
    ax.set_ylabel("time per update step (ms)")
    ax.set_title("HMM update: full graph vs SPRINT subgraphs (k = 1, correct match)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--json", type=Path, help="write the rows as JSON here")
    parser.add_argument("--png", type=Path, help="write the log-log plot here")
    parser.add_argument("--quick", action="store_true", help="3 runs x 50 frames, <= 100k nodes")
    parser.add_argument("--runs", type=int, help="runs per configuration (default 10)")
    parser.add_argument("--steps", type=int, help="frames per run (default 200)")
    parser.add_argument("--max-nodes", type=int, help="largest map (default 1,000,000)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    runs = args.runs or (3 if args.quick else 10)
    steps = args.steps or (50 if args.quick else 200)
    max_nodes = args.max_nodes or (100_000 if args.quick else 1_000_000)
    if runs < 1 or steps < 1 or max_nodes < 1:
        parser.error("--runs, --steps and --max-nodes must be positive")
    nodes = tuple(n for n in NODES if n <= max_nodes)
    print(HEADER)
    rows = bench(nodes, SEQ_LENS, runs, steps, args.seed)
    if args.json:
        args.json.write_text(json.dumps({"rows": rows}, indent=2) + "\n")
    if args.png:
        plot(rows, args.png)
    return 0


if __name__ == "__main__":
    sys.exit(main())
