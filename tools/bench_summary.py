"""Summarising a lifelong map: its size, and the recall of fresh drives before and after.

Per seed, a world of ``T + F`` traversals (the conditions in turn): the first ``T`` are
ingested, merged, into a map that keeps every frame (admission ``all``); a copy of it is
summarised (:meth:`SprintMap.summarize <sprint_map.map.SprintMap.summarize>`, ``--per-place
K``); the last ``F`` traversals, never ingested, are localised on both maps (smoothed, as ingest
decides) and scored by the ground truth: SPRINT recall@1 (the best hypothesis), accepted recall@1
and the precision of accepted answers, over the frames the map can match. The ground truth of a
map's frames is the positions the map stores (a summarised sequence keeps those of its kept
frames), so both maps are scored by what they hold.

    python tools/bench_summary.py --world hard --frames 150 --traversals 24 --fresh 8
    python tools/bench_summary.py --world latent --seeds 0 1 2
    python tools/bench_summary.py --quick          # 8 + 2 traversals x 60 frames, one seed

Prints a table per seed and the mean, writes ``--json``. Figures: ``docs/benchmarks.md``.
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

from sprint_map import MapConfig
from sprint_map.frontend import GroundTruth
from sprint_map.map import SprintMap
from sprint_map.synth import CityConfig
from sprint_map.synth.latent import LatentConfig

if __package__ in (None, ""):  # run as ``python tools/...``: ``tools`` from the checkout
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tools.bench_lifelong import LATENT, WORLDS, Drive, latent_drives, render_drives, score  # noqa: E402


def ingest_all(path: Path, drives: list[Drive], config: MapConfig) -> None:
    """Ingest ``drives`` in turn, merged, into a new map keeping every frame."""
    with SprintMap.create(path, config) as m:
        for drive in drives:
            m.ingest(drive.rows, name=drive.name, positions=drive.positions[:, 1:],
                     thumbnails=drive.thumbnails)


def map_truth(m: SprintMap, spec: Any, fresh: list[Drive]) -> GroundTruth:
    """A ground truth of what ``m`` stores (its stored positions) and of the fresh drives."""
    positions = {d.name: d.positions for d in fresh}
    for seq in m.sequences():
        stored = m.positions(seq.seq_id)
        assert stored is not None
        width = fresh[0].positions.shape[1] - 1  # x, y[, heading]
        positions[seq.name] = np.column_stack([np.arange(seq.length), stored[:, :width]])
    return GroundTruth(spec, positions=positions)


def scores(m: SprintMap, spec: Any, fresh: list[Drive]) -> dict[str, Any]:
    """The fresh drives localised on ``m``, pooled."""
    gt = map_truth(m, spec, fresh)
    names = {s.seq_id: s.name for s in m.sequences()}
    totals: dict[str, int] = {"frames_with_match": 0, "sprint_correct": 0, "accepted": 0,
                              "accepted_correct": 0, "accepted_recall_correct": 0}
    for drive in fresh:
        has_match = gt.has_match(drive.name, np.arange(len(drive.rows)), list(names.values()))
        decisions, _ = m.localize(drive.rows, smooth=True, thumbnails=drive.thumbnails)
        row = score(decisions, drive.name, gt, names, has_match)
        totals["frames_with_match"] += int(has_match.sum())
        for key in ("sprint_correct", "accepted", "accepted_correct",
                    "accepted_recall_correct"):
            totals[key] += row[key]
    matchable = max(totals["frames_with_match"], 1)
    return {**totals,
            "sprint_recall@1": round(totals["sprint_correct"] / matchable, 4),
            "accepted_recall@1": round(totals["accepted_recall_correct"] / matchable, 4),
            "precision": (round(totals["accepted_correct"] / totals["accepted"], 4)
                          if totals["accepted"] else None)}


def run_seed(drives: list[Drive], fresh: int, spec: Any, config: MapConfig, per_place: int,
             work: Path) -> dict[str, Any]:
    """One seed: the map, its summary, the fresh drives on both."""
    kept, held = drives[:-fresh], drives[-fresh:]
    full = work / "everything.map"
    start = time.perf_counter()
    ingest_all(full, kept, config)
    ingest_s = time.perf_counter() - start
    summary = work / "summary.map"
    shutil.copytree(full, summary)
    with SprintMap.open(summary) as m:
        report = m.summarize(per_place)
        check = m.check()
    out: dict[str, Any] = {"ingest_seconds": round(ingest_s, 1), "summary": report,
                           "check_ok": check.ok, "frames_per_drive": len(kept[0].rows)}
    for label, path in (("everything", full), ("summarised", summary)):
        with SprintMap.open(path, readonly=True) as m:
            started = time.perf_counter()
            out[label] = {**scores(m, spec, held), "vertices": m.stats()["vertices"],
                          "disk_bytes": m.store.disk_bytes(),
                          "localize_seconds": round(time.perf_counter() - started, 1)}
    out["traversals_worth"] = round(report["vertices_after"] / len(kept[0].rows), 1)
    out["recall_change_points"] = round(100 * (out["summarised"]["sprint_recall@1"]
                                               - out["everything"]["sprint_recall@1"]), 1)
    out["accepted_change_points"] = round(100 * (out["summarised"]["accepted_recall@1"]
                                                 - out["everything"]["accepted_recall@1"]), 1)
    return out


def print_seed(seed: int, r: dict[str, Any]) -> None:
    s = r["summary"]
    print(f"seed {seed}: {s['vertices_before']} -> {s['vertices_after']} vertices "
          f"({r['traversals_worth']} traversals' worth), {s['sequences_before']} -> "
          f"{s['sequences_after']} sequences, {s['seconds']} s, check "
          f"{'ok' if r['check_ok'] else 'FAILED'}")
    print(f"  {'map':<12}{'R@1':>8}{'accR@1':>8}{'P':>8}{'MB':>8}")
    for label in ("everything", "summarised"):
        x = r[label]
        p = "-" if x["precision"] is None else f"{100 * x['precision']:.1f}"
        print(f"  {label:<12}{100 * x['sprint_recall@1']:>8.1f}"
              f"{100 * x['accepted_recall@1']:>8.1f}{p:>8}{x['disk_bytes'] / 1e6:>8.1f}")
    print(f"  summarised - everything: R@1 {r['recall_change_points']:+.1f}, accepted "
          f"{r['accepted_change_points']:+.1f} points")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--traversals", type=int, default=24, help="traversals ingested")
    parser.add_argument("--fresh", type=int, default=8, help="held-out traversals localised")
    parser.add_argument("--frames", type=int, default=300, help="frames per traversal")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--world", choices=[*sorted(WORLDS), "latent"], default="hard")
    parser.add_argument("--per-place", type=int, default=1, help="summarize --per-place K")
    parser.add_argument("--quick", action="store_true", help="8 + 2 traversals x 60 frames")
    parser.add_argument("--workers", type=int, default=None, help="rendering threads")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args(argv)
    if args.quick:
        args.traversals, args.fresh, args.frames, args.seeds = 8, 2, 60, args.seeds[:1]
    if args.traversals < 2 or args.fresh < 1 or args.frames < 10:
        parser.error("need --traversals >= 2, --fresh >= 1 and --frames >= 10")
    city: CityConfig | LatentConfig = WORLDS.get(args.world, LATENT)
    config = (MapConfig(dim=LATENT.dim) if args.world == "latent"
              else MapConfig.for_descriptor("hog"))
    started = time.perf_counter()
    results = []
    for seed in args.seeds:
        n = args.traversals + args.fresh
        if isinstance(city, LatentConfig):
            drives, gt, _ = latent_drives(seed, n, args.frames, city)
        else:
            drives, gt, _ = render_drives(seed, n, args.frames, city, args.workers)
        with tempfile.TemporaryDirectory() as tmp:
            r = run_seed(drives, args.fresh, gt.spec, config, args.per_place, Path(tmp))
        print_seed(seed, r)
        results.append({"seed": seed, **r})
    mean = {key: round(float(np.mean([r[key] for r in results])), 2)
            for key in ("traversals_worth", "recall_change_points", "accepted_change_points")}
    print(f"mean of {len(results)} seed(s): {mean['traversals_worth']} traversals' worth, "
          f"R@1 {mean['recall_change_points']:+.2f}, accepted "
          f"{mean['accepted_change_points']:+.2f} points; "
          f"{time.perf_counter() - started:.0f} s in all")
    if args.json:
        args.json.write_text(json.dumps({"args": {k: str(v) if isinstance(v, Path) else v
                                                  for k, v in vars(args).items()},
                                         "seeds": results, "mean": mean}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
