#!/usr/bin/env python3
"""Benchmark the map store: ingest rate, open time versus map size, disk bytes per vertex.

Usage::

    python tools/bench_store.py [--json OUT] [--quick] [--workdir DIR] [--dim 256]

Measures, through :meth:`sprint_map.map.SprintMap.add_sequence` and :meth:`SprintMap.open`:

1. ingest rate (descriptors/s) of N x dim float32 descriptors added as sequences of 1000 frames
   (default config: the index is persisted every 200k vertices), of 1000 frames with index
   persistence off, and of 10000 frames; each against a baseline measured in the same run: the
   same bytes appended to one file with an fsync per sequence (the least any durable per-sequence
   commit must cost);
2. open time (median of repeated opens, reader and writer) of a 10k-vertex map and of the
   N-vertex map; ``open_ratio`` is the larger of the two N/10k ratios and must be ~1;
3. disk bytes per vertex (shards, LMDB, index), against the raw descriptor size.

N is 1,000,000 (``--quick``: 100,000). Maps are written under ``--workdir`` (default: a new
directory in /tmp) and deleted afterwards. Prints a table; ``--json`` also writes
``{"rows": [...], "open_ratio": ...}``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map.config import MapConfig, StoreOptions
from sprint_map.map import SprintMap
from sprint_map.storage.store import INDEX_DIR, LMDB_DIR, SHARDS_DIR

OPEN_REPEATS = 31


def allocated(path: Path) -> int:
    """Bytes actually allocated under ``path`` (LMDB's file is sparse)."""
    if path.is_file():
        return path.stat().st_blocks * 512
    return sum(p.stat().st_blocks * 512 for p in path.rglob("*") if p.is_file())


def ingest(path: Path, pool: np.ndarray, seq_len: int, config: MapConfig) -> dict[str, float]:
    """Create a map and add ``pool`` as sequences of ``seq_len``; time adds and close."""
    start = time.perf_counter()
    m = SprintMap.create(path, config)
    for first in range(0, len(pool), seq_len):
        m.add_sequence(pool[first : first + seq_len], name=f"s{first // seq_len}")
    added = time.perf_counter() - start
    assert m.stats()["vertices"] == len(pool)
    m.close()
    total = time.perf_counter() - start
    return {"seconds_add": added, "seconds_total": total, "rate": len(pool) / total}


def baseline_append(path: Path, pool: np.ndarray, seq_len: int) -> float:
    """Descriptors/s appending the same bytes to one file with one fsync per sequence."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    start = time.perf_counter()
    try:
        for first in range(0, len(pool), seq_len):
            view = memoryview(np.ascontiguousarray(pool[first : first + seq_len])).cast("B")
            written = 0
            while written < len(view):
                written += os.write(fd, view[written:])
            os.fsync(fd)
    finally:
        os.close(fd)
    seconds = time.perf_counter() - start
    path.unlink()
    return len(pool) / seconds


def open_medians(paths: list[Path], readonly: bool) -> list[float]:
    """Median seconds of ``SprintMap.open`` of each map (the close is not timed).

    Opens of the maps alternate, so that background activity (e.g. writeback of the files
    just written) weighs on all of them alike rather than on whichever is measured first.
    """
    times: list[list[float]] = [[] for _ in paths]
    for _ in range(OPEN_REPEATS):
        for path, samples in zip(paths, times, strict=True):
            start = time.perf_counter()
            m = SprintMap.open(path, readonly=readonly)
            samples.append(time.perf_counter() - start)
            m.close()
    return [statistics.median(samples) for samples in times]


def first_search(path: Path, query: np.ndarray) -> float:
    """Seconds of the first search after an open: the lazy index load (read the persisted
    file) happens here, not in the open."""
    with SprintMap.open(path, readonly=True) as m:
        start = time.perf_counter()
        m.search(query, k=10)
        return time.perf_counter() - start


def row(name: str, value: float, unit: str, baseline: float | None = None,
        baseline_name: str = "", **extra: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"name": name, "value": value, "unit": unit}
    if baseline is not None:
        out.update(baseline=baseline, baseline_name=baseline_name, ratio=value / baseline)
    out.update(extra)
    return out


def run(work: Path, n: int, dim: int, small: int, log: Any) -> dict[str, Any]:
    rng = np.random.default_rng(0)
    log(f"generating {n} x {dim} float32 descriptors ({n * dim * 4 / 2**30:.2f} GiB)")
    pool = rng.standard_normal((n, dim), dtype=np.float32)
    rows: list[dict[str, Any]] = []

    def ingest_row(label: str, seq_len: int, config: MapConfig, keep: bool = False
                   ) -> Path:
        path = work / label.replace(" ", "_").replace(",", "")
        log(f"ingest: {label}")
        result = ingest(path, pool, seq_len, config)
        base = baseline_append(work / "baseline.f32", pool, seq_len)
        rows.append(row(f"ingest {label}", result["rate"], "descriptors/s", base,
                        f"append+fsync per {seq_len} rows", seconds=result["seconds_total"],
                        seconds_close=result["seconds_total"] - result["seconds_add"],
                        vertices=n, seq_len=seq_len))
        if not keep:
            shutil.rmtree(path)
        return path

    big = ingest_row(f"{n} x {dim}, 1000/seq", 1000, MapConfig(dim=dim), keep=True)

    # Open time: a 10k-vertex map against the big one, both in their steady state: closed,
    # with the index persisted (a search loads it, the writer's close persists it).
    small_path = work / "small"
    log(f"open time: {small} vs {n} vertices")
    with SprintMap.create(small_path, MapConfig(dim=dim)) as m:
        for first in range(0, small, 1000):
            m.add_sequence(pool[first : first + 1000])
    for path in (small_path, big):
        with SprintMap.open(path) as m:
            m.search(pool[:1], k=1)
    os.sync()  # start from clean page cache state: no writeback of the maps just written
    ratios = []
    for readonly, who in ((True, "reader"), (False, "writer")):
        t_small, t_big = open_medians([small_path, big], readonly)
        ratios.append(t_big / t_small)
        rows.append(row(f"open ({who}), {small} vertices", t_small * 1e3, "ms"))
        rows.append(row(f"open ({who}), {n} vertices", t_big * 1e3, "ms", t_small * 1e3,
                        f"open ({who}), {small} vertices"))
    query = pool[:1]
    rows.append(row(f"first search (index load), {small} vertices",
                    first_search(small_path, query) * 1e3, "ms"))
    t_file = first_search(big, query)
    rows.append(row(f"first search (index load), {n} vertices", t_file * 1e3, "ms"))
    # The flat index file duplicates the shards; how long would building it from them take?
    aside = work / "index-aside"
    (big / INDEX_DIR).rename(aside)
    (big / INDEX_DIR).mkdir()
    rows.append(row(f"first search (index rebuilt from shards), {n} vertices",
                    first_search(big, query) * 1e3, "ms", t_file * 1e3,
                    "first search (index load)"))
    shutil.rmtree(big / INDEX_DIR)
    aside.rename(big / INDEX_DIR)

    # Disk use of the big map (closed: shards, LMDB and the persisted index).
    raw = dim * 4
    parts = {
        "shards": allocated(big / SHARDS_DIR),
        "lmdb": allocated(big / LMDB_DIR),
        "index": allocated(big / INDEX_DIR),
    }
    total = allocated(big)
    rows.append(row("disk bytes/vertex, total", total / n, "B", raw, "raw float32 descriptor"))
    for part, size in parts.items():
        rows.append(row(f"disk bytes/vertex, {part}", size / n, "B", raw,
                        "raw float32 descriptor"))
    shutil.rmtree(big)
    shutil.rmtree(small_path)

    ingest_row(f"{n} x {dim}, 1000/seq, index persist off", 1000,
               MapConfig(dim=dim, store=StoreOptions(index_persist_every=1 << 62)))
    ingest_row(f"{n} x {dim}, 10000/seq", 10000, MapConfig(dim=dim))
    return {"rows": rows, "open_ratio": max(ratios)}


def print_table(result: dict[str, Any]) -> None:
    print(f"{'measure':<58} {'value':>14} {'unit':<14} {'baseline':>12} {'ratio':>8}")
    for r in result["rows"]:
        base = f"{r['baseline']:12.4g}" if "baseline" in r else " " * 12
        ratio = f"{r['ratio']:8.3f}" if "ratio" in r else ""
        print(f"{r['name']:<58} {r['value']:14.6g} {r['unit']:<14} {base} {ratio}")
    print(f"open_ratio (max of reader/writer, big/small): {result['open_ratio']:.3f}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", type=Path, help="also write the results as JSON here")
    parser.add_argument("--quick", action="store_true", help="100k vertices instead of 1M")
    parser.add_argument("--dim", type=int, default=256)
    parser.add_argument("--workdir", type=Path, help="parent of the scratch dir (default /tmp)")
    args = parser.parse_args(argv)
    n = 100_000 if args.quick else 1_000_000

    def log(message: str) -> None:
        print(f"[bench_store] {message}", file=sys.stderr, flush=True)

    work = Path(tempfile.mkdtemp(prefix="sprint-bench-", dir=args.workdir or "/tmp"))
    try:
        result = run(work, n, args.dim, 10_000, log)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result["config"] = {"vertices": n, "dim": args.dim, "quick": args.quick,
                        "open_repeats": OPEN_REPEATS}
    print_table(result)
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
