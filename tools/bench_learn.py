"""Does a map that learns its descriptor from its own merges retrieve better? (issue 33)

Nordland, each direction: a map of one season plus the first half of the other ingested
(localised and merged), then a copy of it learns its projection from its merged edges
(``SprintMap.learn``, what ``sprint-map index MAP --learn`` runs). The second half of the other
season is then, on both maps (the baseline is the same map without learning, in the same run):

* searched: exact k-NN@1 (the map's index is flat at this size), tolerance +/- 1 frame, a hit
  on either season counted by its frame;
* localised causally (``localize``, streaming): SPRINT recall@1 (``best`` place);
* ingested (smoothed decisions, the merge rule): merge precision of the edges it adds.

    python tools/bench_learn.py --cache /tmp/hog --json learn.json

``--scale N --dim D`` instead times learning from N synthetic merged edges (a map of N
vertices, every vertex of its second half joined to one of the first) and rebuilding the index
of the map with the projection, in this process (the cost target: 1M in under 2 minutes).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map import MapConfig, SprintMap

DATASET = Path("/work/shared/data/nordland")


def hog(dataset: Path, name: str, cache: Path | None) -> np.ndarray:
    """HoG of one traversal (the map's descriptor), cached as ``<cache>/nordland_<name>.npy``."""
    if cache is not None and (cache / f"{dataset.name}_{name}.npy").exists():
        return np.load(cache / f"{dataset.name}_{name}.npy")
    from sprint_map.frontend.dataset import Dataset
    from sprint_map.frontend.descriptors import DescriptorSpec

    rows = Dataset.open(dataset, {"alignment": "frame"})[name].open(
        DescriptorSpec("hog", {})).read_all()
    if cache is not None:
        cache.mkdir(parents=True, exist_ok=True)
        np.save(cache / f"{dataset.name}_{name}.npy", rows)
    return rows


def measure(m: SprintMap, queries: np.ndarray, first: int, tol: int) -> dict[str, Any]:
    """k-NN@1, causal SPRINT recall@1, then ingest: merge precision; frame ``first + i`` is
    query ``i``'s place (same frame number in either season)."""
    truth = first + np.arange(len(queries))
    _, ids = m.search(queries, 1)
    located = m.locate(ids[:, 0].tolist())
    knn = np.mean([abs(img - t) <= tol for (_, img), t in zip(located, truth, strict=True)])
    t0 = time.perf_counter()
    causal, _ = m.localize(queries)
    localize_s = time.perf_counter() - t0
    sprint = np.mean([d.best is not None and abs(d.best[1] - truth[d.frame]) <= tol
                      for d in causal])
    accepted = [d for d in causal if d.is_match]
    result = m.ingest(queries, name="second-half")
    merged = [d for d, keep in zip(result.decisions, np.asarray(result.merged).tolist(),
                                   strict=True) if keep]
    wrong = sum(abs(int(d.image_id or 0) - truth[d.frame]) > tol for d in merged)
    return {"knn@1": round(float(knn), 4), "sprint_causal_recall@1": round(float(sprint), 4),
            "accepted_precision": round(float(np.mean(
                [abs(int(d.image_id or 0) - truth[d.frame]) <= tol for d in accepted])), 4)
            if accepted else None,
            "merged": len(merged), "merged_wrong": int(wrong),
            "merge_precision": round(1 - wrong / len(merged), 4) if merged else None,
            "localize_ms_per_frame": round(1e3 * localize_s / len(queries), 2)}


def nordland(args: argparse.Namespace) -> dict[str, Any]:
    seasons = {name: hog(args.dataset, name, args.cache) for name in ("summer", "winter")}
    out: dict[str, Any] = {}
    work = Path(tempfile.mkdtemp(prefix="bench-learn-"))
    try:
        for db, other in (("summer", "winter"), ("winter", "summer")):
            a, b = seasons[db], seasons[other]
            half = len(b) // 2
            plain = work / f"{db}-plain.map"
            t0 = time.perf_counter()
            with SprintMap.create(plain, MapConfig.for_descriptor("hog")) as m:
                m.add_sequence(a, name=db)
                m.ingest(b[:half], name=f"{other}-first-half")
                edges = m.stats()["edges"]
            build_s = time.perf_counter() - t0
            learned = work / f"{db}-learned.map"
            shutil.copytree(plain, learned)
            t0 = time.perf_counter()
            with SprintMap.open(learned) as m:
                report = m.learn()
            learn_s = time.perf_counter() - t0
            row: dict[str, Any] = {"map_edges": edges, "build_s": round(build_s, 1),
                                   "learn": report, "learn_s": round(learn_s, 1)}
            for arm, path in (("without", plain), ("with", learned)):
                with SprintMap.open(path) as m:
                    row[arm] = measure(m, b[half:], half, args.tolerance)
            row["gain_points"] = {key: round(100 * (row["with"][key] - row["without"][key]), 1)
                                  for key in ("knn@1", "sprint_causal_recall@1")}
            out[f"{db}->{other}"] = row
            print_row(f"{db} + first half of {other}; second half of {other} localised", row)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return out


def print_row(title: str, row: dict[str, Any]) -> None:
    def pct(v: float | None) -> str:
        return "-" if v is None else f"{100 * v:.1f} %"
    learn = row["learn"]
    print(f"\n{title}\n  map: {row['map_edges']} edges; learn: {learn['pairs']} pairs, "
          f"{learn['dim_in']} -> {learn['dim_out']} dims, adopted {learn['adopted']}, held-back "
          f"recall@1 {pct(learn['heldout_recall_before'])} -> "
          f"{pct(learn['heldout_recall_after'])} ({row['learn_s']} s)")
    print(f"  {'':>8} {'kNN@1':>7} {'SPRINT@1':>9} {'acc.prec':>8} {'merged':>6} "
          f"{'wrong':>5} {'merge prec':>10} {'ms/frame':>8}")
    for arm in ("without", "with"):
        r = row[arm]
        print(f"  {arm:>8} {pct(r['knn@1']):>7} {pct(r['sprint_causal_recall@1']):>9} "
              f"{pct(r['accepted_precision']):>8} {r['merged']:>6} {r['merged_wrong']:>5} "
              f"{pct(r['merge_precision']):>10} {r['localize_ms_per_frame']:>8}")
    print(f"  gain (points): {row['gain_points']}", flush=True)


def scale(args: argparse.Namespace) -> dict[str, Any]:
    """Learn from ``args.scale`` synthetic edges and rebuild the index of that many vertices."""
    n, dim = args.scale, args.dim
    half = n // 2
    rng = np.random.default_rng(0)
    work = Path(tempfile.mkdtemp(prefix="bench-learn-scale-"))
    try:
        config = MapConfig.from_dict({"dim": dim})
        path = work / "scale.map"
        t0 = time.perf_counter()
        with SprintMap.create(path, config) as m:
            store = m.store
            place = rng.standard_normal((half, dim)).astype(np.float32)
            # the second condition: a loud nuisance in 16 directions, as a season is
            nuisance = np.linalg.qr(rng.standard_normal((dim, 16)))[0].astype(np.float32)
            from sprint_map.storage.records import EdgeSpec

            for lo in range(0, half, 65536):  # drives of 65,536 frames
                rows = place[lo: lo + 65536] + 0.3 * rng.standard_normal(
                    (min(65536, half - lo), dim)).astype(np.float32)
                store.add_sequence(rows, name=f"a{lo}")
            first_seqs = {s.name: s.seq_id for s in store.sequences()}
            for lo in range(0, half, 65536):
                k = min(65536, half - lo)
                rows = (place[lo: lo + k] + 0.3 * rng.standard_normal((k, dim)).astype(
                    np.float32) + 15 * rng.standard_normal((k, 16)).astype(np.float32)
                    @ nuisance.T)
                seq = first_seqs[f"a{lo}"]
                store.add_sequence(rows, name=f"b{lo}", edges=[  # both ways, as merges are
                    e for i in range(k) for e in (EdgeSpec((None, i), (seq, i)),
                                                  EdgeSpec((seq, i), (None, i)))])
            m.flush()
            build_s = time.perf_counter() - t0
            stats = m.stats()
        shutil.copytree(path, work / "plain.map")  # the same map without learning
        with SprintMap.open(path) as m:
            t0 = time.perf_counter()
            report = m.learn()
            learn_s = time.perf_counter() - t0
            index = m.info()["index"]
            queries = (place[:300] + 0.3 * rng.standard_normal((300, dim))).astype(np.float32)
            with SprintMap.open(work / "plain.map", readonly=True) as plain:
                # single-query searches, as localisation makes them, alternating between the
                # two maps so that the machine's load weighs on both alike
                times: dict[str, list[float]] = {"without": [], "with": []}
                for mp in (plain, m):
                    mp.search(queries[:1], 10)
                for q in queries:
                    for arm, mp in (("without", plain), ("with", m)):
                        t = time.perf_counter()
                        mp.search(q[None], 10)
                        times[arm].append(time.perf_counter() - t)
            search_before, search_after = (round(1e3 * float(np.median(times[a])), 3)
                                           for a in ("without", "with"))
        out = {"vertices": stats["vertices"], "edges": stats["edges"], "dim": dim,
               "build_s": round(build_s, 1), "learn_and_rebuild_s": round(learn_s, 1),
               "learn": report, "index": index,
               "search_p50_ms": {"without": search_before, "with": search_after}}
        print(f"{stats['vertices']} vertices, {stats['edges']} edges, dim {dim}: learning and "
              f"rebuilding the index took {learn_s:.1f} s (adopted {report['adopted']}, "
              f"held-back recall@1 {report['heldout_recall_before']:.3f} -> "
              f"{report['heldout_recall_after']:.3f}); index {index['type']}; single-query "
              f"search p50 {search_before} ms without, {search_after} ms with", flush=True)
        return out
    finally:
        shutil.rmtree(work, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--dataset", type=Path, default=DATASET)
    parser.add_argument("--cache", type=Path, help="HoG cache directory")
    parser.add_argument("--tolerance", type=int, default=1, help="+/- frames counted correct")
    parser.add_argument("--scale", type=int, help="time learning from this many edges instead")
    parser.add_argument("--dim", type=int, default=128, help="--scale: descriptor dimension")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    result = scale(args) if args.scale else nordland(args)
    result = {"args": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
              "results": result, "seconds": round(time.perf_counter() - started, 1)}
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
