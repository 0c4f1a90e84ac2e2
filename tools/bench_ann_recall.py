"""ANN recall@k of the approximate indexes against exact search, on real descriptors.

Builds a map of the database descriptors in each index configuration (PCA, IVF with PQ or SQ8
codes in sealed segments, exact re-ranking), searches it with the query descriptors and
compares the k nearest with exact brute force over the same rows; the flat index is the
baseline in the same run (recall 1 by construction, and its latency)::

    python tools/bench_ann_recall.py --dataset /work/shared/data/nordland --database summer \\
        --query winter --json ann.json
    python tools/bench_ann_recall.py --database-npy db.npy --query-npy q.npy --nlist 64

Descriptors of a data set are the map's HoG (1764 dims), computed once (``--cache DIR``).
``--segment-rows`` is small so that the whole database is sealed into IVF segments, as in a
large map (a small tail would be searched exactly and flatter the recall).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map.config import MapConfig
from sprint_map.storage.store import MapStore


def hog_rows(dataset: Path, name: str, cache: Path | None) -> np.ndarray:
    """HoG descriptors of one traversal (cached as ``<cache>/<dataset>_<name>.npy``)."""
    if cache is not None:
        path = cache / f"{dataset.name}_{name}.npy"
        if path.exists():
            return np.load(path)
    from sprint_map.frontend.dataset import Dataset
    from sprint_map.frontend.descriptors import DescriptorSpec

    rows = Dataset.open(dataset, {"alignment": "frame"})[name].open(
        DescriptorSpec("hog", {})).read_all()
    if cache is not None:
        cache.mkdir(parents=True, exist_ok=True)
        np.save(cache / f"{dataset.name}_{name}.npy", rows)
    return rows


def exact_knn(db: np.ndarray, queries: np.ndarray, k: int) -> np.ndarray:
    d = (queries ** 2).sum(1)[:, None] - 2 * queries @ db.T + (db ** 2).sum(1)[None, :]
    return np.argsort(d, axis=1, kind="stable")[:, :k]


def measure(db: np.ndarray, queries: np.ndarray, truth: np.ndarray, k: int,
            overrides: dict[str, Any], workdir: Path) -> dict[str, Any]:
    """Build a map of ``db`` with ``overrides``, search ``queries`` one at a time."""
    path = Path(tempfile.mkdtemp(dir=workdir)) / "m.map"
    config = MapConfig.from_dict({"dim": db.shape[1], **overrides})
    t0 = time.perf_counter()
    with MapStore.create(path, config) as store:
        store.add_sequence(db, name="database")
        store.search(queries[:1], k)  # trains (if approximate) and loads
        build_s = time.perf_counter() - t0
        desc = store.index.describe()
        got = np.empty((len(queries), k), dtype=np.int64)
        times = []
        for i, row in enumerate(queries):
            t = time.perf_counter()
            _, ids = store.search(row[None], k)
            times.append(time.perf_counter() - t)
            got[i] = ids[0]
    recall = np.mean([len(set(g) & set(t)) for g, t in zip(got.tolist(), truth.tolist(),
                                                           strict=True)]) / k
    top1 = float(np.mean(got[:, 0] == truth[:, 0]))
    return {"config": overrides, "index": desc["type"], "segments": desc.get("segments", 0),
            "tail": desc.get("tail", 0), "recall_at_k": float(recall), "top1_agrees": top1,
            "search_p50_ms": 1e3 * float(np.median(times)), "build_s": build_s}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", type=Path, default=Path("/work/shared/data/nordland"))
    parser.add_argument("--database", default="summer")
    parser.add_argument("--query", default="winter")
    parser.add_argument("--database-npy", type=Path)
    parser.add_argument("--query-npy", type=Path)
    parser.add_argument("--cache", type=Path, help="cache the HoG descriptors here")
    parser.add_argument("--k", type=int, default=10)
    parser.add_argument("--nlist", type=int, default=64)
    parser.add_argument("--segment-rows", type=int, default=256)
    parser.add_argument("--nprobe", type=int, nargs="+", default=[8, 16])
    parser.add_argument("--kinds", nargs="+", default=["ivf-pq", "ivf-sq8"])
    parser.add_argument("--workdir", type=Path)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    if args.database_npy:
        db, queries = np.load(args.database_npy), np.load(args.query_npy)
    else:
        db = hog_rows(args.dataset, args.database, args.cache)
        queries = hog_rows(args.dataset, args.query, args.cache)
    db, queries = db.astype(np.float32), queries.astype(np.float32)
    truth = exact_knn(db, queries, args.k)
    configs: list[dict[str, Any]] = [{"index_type": "flat"}]
    for kind in args.kinds:
        for nprobe in args.nprobe:
            configs.append({"index_type": kind, "index_nlist": args.nlist,
                            "index_nprobe": min(nprobe, args.nlist),
                            "index_segment_rows": args.segment_rows})
    rows = []
    print(f"database {len(db)} x {db.shape[1]}, {len(queries)} queries, recall@{args.k}")
    print(f"{'index':<38} {'nprobe':>6} {'segs':>5} {'recall':>7} {'top1':>6} {'p50 ms':>7}")
    with tempfile.TemporaryDirectory(dir=args.workdir) as work:
        for overrides in configs:
            row = measure(db, queries, truth, args.k, overrides, Path(work))
            rows.append(row)
            print(f"{row['index']:<38} {overrides.get('index_nprobe', '-'):>6} "
                  f"{row['segments']:>5} {row['recall_at_k']:>7.3f} {row['top1_agrees']:>6.3f} "
                  f"{row['search_p50_ms']:>7.2f}", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "database": len(db),
                                         "queries": len(queries), "k": args.k}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
