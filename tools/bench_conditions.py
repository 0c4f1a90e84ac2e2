"""Conditions: does a lifelong map answer by place, not by condition (issue 51)?

Drives of several conditions (seasons, and per drive its own exposure and noise) are merged into
one map in turn through the public API (``SprintMap.ingest``, merge on, the defaults or the
``--set`` levers). Before each drive is merged it is answered three ways, all read-only:

- against the **whole map** (every earlier drive): causal (the streamed decisions a vehicle
  gets, :func:`~sprint_map.evaluation.runner.evaluate_query`) and smoothed (``ingest``'s own
  decisions, the ones it merges);
- against the map of **only the drives that hold its places** (the earlier drives with a true
  match for at least one of its frames): a copy of the map with the other drives removed
  (``SprintMap.remove_sequences``: their edges go, the holders' own merges stay). Both maps
  answer the same frames, so ``alias cost = whole - holders`` (points) is what the drives of
  other places cost the query: condition aliasing, when they share its condition. A drive whose
  holders are every earlier drive has no alias cost by construction (``holders: all``);
- in the later half, also against a copy of the map as it stood before the later half (the
  *snapshot*), scored on the frames the snapshot can match: ``grown - before`` is what growing
  the map did to the same frames.

Reported per drive: recall@1 (the decision's most probable place is a true match, over the frames
with one), accepted recall (an accepted decision and right), k-NN@1, the alias costs, the merged
decisions and how many are wrong, and the frames of unmapped places (no true match) merged.
Summary per arm: alias cost pooled over the drives whose holders are not the whole map (and the
worst drive), accepted recall of the earlier vs the later half of the stream, merge precision,
the share of unmapped frames merged, snapshot ``grown - before``; the issue's targets are
``alias >= -2`` points, later >= earlier, merge precision >= 99 %, unmapped merged <= 1 %.

Worlds (``--world``):

- ``latent``: :mod:`sprint_map.synth.latent` with seasons (summer, summer, winter, winter in turn)
  and its six conditions; 40 % of each drive's frames on streets no earlier drive saw;
- ``city``: :mod:`sprint_map.synth.city`, rendered images described by HoG, with seasons
  (:mod:`sprint_map.synth.seasons`: snow and snowbanks, or foliage) over its conditions;
- ``nordland``: the real ride (``--nordland``, summer + winter, 3,576 frame-aligned frames each,
  true match within +/- 1 frame) cut into ``--segments`` segments; each drive is 2-4 consecutive
  segments of one season (drawn from the seed), with its own exposure (gamma U(0.7, 1.4)) and
  sensor noise (sigma U(2, 6) grey levels) applied to the images before HoG.

Levers: ``--set KEY=VALUE`` changes the map config of every arm (``MapConfig.replace``: flat keys
such as ``merge_min_run=8`` or ``index_type=flat``; ``part.field=VALUE`` for a field of a part,
e.g. ``hmm.k=20``; values are JSON, else text). ``--arm 'LABEL KEY=VALUE ...'`` adds an arm
with those changes on top, run on the same drives beside the defaults, and the summary gives
each arm minus ``default``.

    python tools/bench_conditions.py --world latent --quick              # ~1 min, 2 cores
    python tools/bench_conditions.py --world city --seeds 0 1 2 --quick
    python tools/bench_conditions.py --world nordland --json nordland-conditions.json
    python tools/bench_conditions.py --world latent --arm 'minrun merge_min_run=8'

``--quick``: latent and city 8 drives x 80 frames; Nordland the first 1,200 frames of the ride
in 8 segments, 6 drives. Cost per drive: four localisations of it (whole map, holders, ingest,
and the snapshot in the later half) and one map copy.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map import MapConfig
from sprint_map.evaluation.runner import evaluate_query
from sprint_map.frontend import GroundTruth, GroundTruthSpec
from sprint_map.localize.localizer import FrameDecision
from sprint_map.map import SprintMap
from sprint_map.synth.latent import LatentConfig, make_latent
from tools.bench_lifelong import score

KS = (1, 10)
#: The seasons in turn over the drives of the generated worlds.
SEASON_CYCLE = ("summer", "summer", "winter", "winter")
LATENT = LatentConfig(grid=(5, 5), novel_fraction=0.4, reverse_fraction=0.05,
                      seasons=SEASON_CYCLE)
#: The city's conditions (one per drive in turn) under the seasons.
CITY_CONDITIONS = ("day", "overcast", "dusk", "rain")
#: The issue's exposure and noise ranges of a Nordland drive.
GAMMA = (0.7, 1.4)
NOISE = (2.0, 6.0)


@dataclasses.dataclass
class Drive:
    """One drive of the stream: its descriptors and what it was driven under."""

    name: str
    season: str
    condition: str
    rows: np.ndarray  # (N, dim) float32


@dataclasses.dataclass
class World:
    """Drives in stream order, their ground truth, and the map config they fit."""

    name: str
    drives: list[Drive]
    gt: GroundTruth
    config: MapConfig
    about: dict[str, Any]


def latent_world(seed: int, drives: int, frames: int, strength: float | None) -> World:
    """The latent family with seasons (``strength``: override of ``season_strength``)."""
    config = LATENT if strength is None else dataclasses.replace(LATENT, season_strength=strength)
    world = make_latent(drives, frames, seed, config)
    out = [Drive(t.name, t.season or "-", t.condition, t.descriptors) for t in world.traversals]
    return World("latent", out, world.ground_truth(), MapConfig(dim=config.dim),
                 {"config": config.to_dict()})


def city_world(seed: int, drives: int, frames: int, strength: float | None) -> World:
    """The rendered city with seasons, described by HoG (``strength``: of the seasons)."""
    from sprint_map.synth import CityConfig, iter_city

    config = CityConfig(grid=(4, 4), novel_fraction=0.4, reverse_fraction=0.05,
                        conditions=CITY_CONDITIONS, seasons=SEASON_CYCLE)
    if strength is not None:
        config = dataclasses.replace(config, season_strength=strength)
    map_config = MapConfig.for_descriptor("hog")
    spec = map_config.descriptor_spec()
    assert spec is not None
    out, positions = [], {}
    for t in iter_city(drives, frames, seed=seed, config=config, workers=2):
        out.append(Drive(t.name, t.plan.season or "-", t.condition, spec.describe_batch(t.images)))
        positions[t.name] = t.positions
    gt = GroundTruth(config.ground_truth_spec(), positions=positions)
    return World("city", out, gt, map_config, {"config": config.to_dict()})


def nordland_drives(seed: int, root: Path, frames: int, segments: int, drives: int
                    ) -> World:
    """The lead's cut of Nordland: the first ``frames`` frames of the ride in ``segments``
    equal segments; each drive 2-4 consecutive segments of one season, its images under its own
    gamma and sensor noise, then HoG. Ground truth: the ride's frame index, +/- 1 frame."""
    import cv2

    map_config = MapConfig.for_descriptor("hog")
    spec = map_config.descriptor_spec()
    assert spec is not None
    files = sorted((root / "summer").glob("*.png"))[:frames]
    if not files:
        raise SystemExit(f"{root}: no summer/*.png (Nordland not found; pass --nordland)")
    images = {}
    for season in ("summer", "winter"):
        frames_read = []
        for f in files:
            image = cv2.imread(str(root / season / f.name))
            if image is None:
                raise SystemExit(f"{root / season / f.name}: cannot read the image")
            frames_read.append(image)
        images[season] = np.stack(frames_read)
    bounds = np.linspace(0, len(files), segments + 1).round().astype(int)
    rng = np.random.default_rng([seed, 51])
    out, positions, about = [], {}, []
    for i in range(drives):
        length = int(rng.integers(2, 5))
        first = int(rng.integers(0, segments - length + 1))
        season = ("summer", "winter")[int(rng.integers(2))]
        gamma, sigma = float(rng.uniform(*GAMMA)), float(rng.uniform(*NOISE))
        ride = np.arange(bounds[first], bounds[first + length])
        levels = 255.0 * (np.arange(256) / 255.0) ** gamma
        shot = levels[images[season][ride]] + rng.normal(0, sigma, images[season][ride].shape)
        pictures = np.clip(shot, 0, 255).astype(np.uint8)
        name = f"d{i:02d}-{season}"
        out.append(Drive(name, season, f"g{gamma:.2f}/n{sigma:.1f}", spec.describe_batch(pictures)))
        positions[name] = np.column_stack([np.arange(len(ride)), ride, np.zeros(len(ride))])
        about.append({"name": name, "season": season, "segments": [first, first + length],
                      "ride_frames": [int(ride[0]), int(ride[-1]) + 1],
                      "gamma": round(gamma, 3), "noise": round(sigma, 2)})
    gt = GroundTruth(GroundTruthSpec("position", radius_m=1.0), positions=positions)
    return World("nordland", out, gt, map_config,
                 {"root": str(root), "frames": len(files), "segments": segments, "drives": about})


def default_nordland() -> Path | None:
    """Where the Nordland set is: :func:`~sprint_map.evaluation.demo.find_nordland`'s places
    (``$SPRINT_MAP_NORDLAND`` first), else ``shared/data/nordland`` beside a parent of this
    checkout."""
    from sprint_map.evaluation.demo import find_nordland

    found = find_nordland()
    if found is not None:
        return found
    for parent in Path(__file__).resolve().parents:
        if (parent / "shared" / "data" / "nordland" / "summer").is_dir():
            return parent / "shared" / "data" / "nordland"
    return None


def apply_sets(config: MapConfig, sets: list[str]) -> MapConfig:
    """``config`` with ``KEY=VALUE`` changes (see the module docstring); a bad key or value is
    the config's own ConfigError."""
    changes: dict[str, Any] = {}
    base = config.to_dict()
    for item in sets:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise SystemExit(f"--set/--arm: expected KEY=VALUE, got {item!r}")
        try:
            value = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        if "." in key:
            part, field = key.split(".", 1)
            nested = changes.setdefault(part, dict(base.get(part) or {}))
            nested[field] = value
        else:
            changes[key] = value
    return config.replace(**changes) if changes else config


def _decisions_score(decisions: list[FrameDecision], drive: Drive, gt: GroundTruth,
                     names: dict[int, str], has_match: np.ndarray, prefix: str) -> dict[str, Any]:
    out = score(decisions, drive.name, gt, names, has_match)
    return {f"{prefix}_{key}": out[key] for key in
            ("sprint_correct", "sprint_recall@1", "accepted_recall_correct", "accepted_recall@1",
             "accepted", "accepted_correct")}


def answer(m: SprintMap, drive: Drive, gt: GroundTruth, prefix: str) -> dict[str, Any]:
    """The drive answered by ``m``, read-only: k-NN, causal and smoothed, scored over the
    frames with a true match in ``m``; keys prefixed ``prefix_``."""
    names = {s.seq_id: s.name for s in m.sequences()}
    knn, causal = evaluate_query(m, drive.name, drive.rows, gt, KS, None)
    smoothed, _ = m.localize(drive.rows, smooth=True)
    has = knn.has_match
    out = {f"{prefix}_frames_with_match": int(has.sum()),
           **{f"{prefix}_knn_recall@{k}": round(float((knn.knn_correct[:, :k].any(axis=1)
                                                       & has).sum()) / max(int(has.sum()), 1), 4)
              for k in KS}}
    out.update(_decisions_score(causal, drive, gt, names, has, f"{prefix}_causal"))
    out.update(_decisions_score(smoothed, drive, gt, names, has, f"{prefix}_smoothed"))
    return out


def run_stream(world: World, config: MapConfig, work: Path) -> list[dict[str, Any]]:
    """Merge the world's drives in turn into a fresh map; one row per drive after the first."""
    drives, gt = world.drives, world.gt
    split = len(drives) // 2
    path, snap_path, hold_path = work / "map", work / "snapshot", work / "holders"
    snapshot: SprintMap | None = None
    rows: list[dict[str, Any]] = []
    m = SprintMap.create(path, config)
    try:
        for i, drive in enumerate(drives):
            if i == split:
                m.close()
                shutil.copytree(path, snap_path)
                snapshot = SprintMap.open(snap_path, readonly=True)
                m = SprintMap.open(path)
            if i == 0:
                m.ingest(drive.rows, name=drive.name, merge=True)
                continue
            start = time.perf_counter()
            frames = np.arange(len(drive.rows))
            earlier = [d.name for d in drives[:i]]
            holders = [n for n in earlier if gt.has_match(drive.name, frames, n).any()]
            row: dict[str, Any] = {"drive": i, "name": drive.name, "season": drive.season,
                                   "condition": drive.condition, "frames": len(drive.rows),
                                   "holders": holders, "holders_all": holders == earlier}
            whole = answer(m, drive, gt, "whole")
            row.update(whole)
            if holders and not row["holders_all"]:
                m.close()
                shutil.copytree(path, hold_path)
                try:
                    with SprintMap.open(hold_path) as held:
                        held.remove_sequences([n for n in earlier if n not in holders])
                        row.update(answer(held, drive, gt, "holders"))
                finally:
                    shutil.rmtree(hold_path)
                m = SprintMap.open(path)
            else:
                row.update({key.replace("whole_", "holders_", 1): value
                            for key, value in whole.items()})
            for kind in ("causal", "smoothed"):
                row[f"alias_{kind}_points"] = round(100 * (
                    row[f"whole_{kind}_sprint_recall@1"]
                    - row[f"holders_{kind}_sprint_recall@1"]), 2)
            if snapshot is not None:
                before = answer(snapshot, drive, gt, "snapshot")
                snap_names = [s.name for s in snapshot.sequences()]
                has = gt.has_match(drive.name, frames, snap_names)
                names = {s.seq_id: s.name for s in m.sequences()}
                grown, _ = m.localize(drive.rows, smooth=True)
                row.update(before)
                row.update(_decisions_score(grown, drive, gt, names, has, "grown_on_snapshot"))
            names = {s.seq_id: s.name for s in m.sequences()}
            result = m.ingest(drive.rows, name=drive.name, merge=True)
            has = gt.has_match(drive.name, frames, earlier)
            merged = np.asarray(result.merged, dtype=bool)
            if not len(merged):
                merged = np.zeros(len(frames), dtype=bool)
            right = np.array([d.seq_id is not None and d.image_id is not None and bool(
                gt.correct(drive.name, d.frame, names[d.seq_id], d.image_id))
                for d in result.decisions], dtype=bool)
            row.update(merged=int(merged.sum()), merged_wrong=int((merged & ~(right & has)).sum()),
                       unmapped=int((~has).sum()), unmapped_merged=int((merged & ~has).sum()),
                       edges_added=result.edges_added,
                       ingest_smoothed_recall_correct=int(
                           (np.array([d.best is not None and bool(gt.correct(
                               drive.name, d.frame, names[d.best[0]], d.best[1]))
                               for d in result.decisions]) & has).sum()),
                       seconds=round(time.perf_counter() - start, 2))
            rows.append(row)
    finally:
        m.close()
        if snapshot is not None:
            snapshot.close()
    return rows


def _ratio(num: float, den: float) -> float | None:
    return round(num / den, 4) if den else None


def summarise(rows: list[dict[str, Any]], split: int) -> dict[str, Any]:
    """Pooled figures of one arm's rows (``split``: first drive of the later half)."""
    def pooled(sel: list[dict[str, Any]], prefix: str, key: str) -> float | None:
        return _ratio(sum(r[f"{prefix}_{key}"] for r in sel),
                      sum(r[f"{prefix.split('_')[0]}_frames_with_match"] for r in sel))

    aliased = [r for r in rows if not r["holders_all"] and r["holders"]]
    out: dict[str, Any] = {"aliased_drives": len(aliased)}
    for kind in ("causal", "smoothed"):
        whole = pooled(aliased, f"whole_{kind}", "sprint_correct")
        held = pooled(aliased, f"holders_{kind}", "sprint_correct")
        out[f"alias_{kind}"] = {
            "whole_recall@1": whole, "holders_recall@1": held,
            "points": None if whole is None or held is None else round(100 * (whole - held), 2),
            "worst_drive_points": min((r[f"alias_{kind}_points"] for r in aliased), default=None)}
    for half, sel in (("earlier", [r for r in rows if r["drive"] < split]),
                      ("later", [r for r in rows if r["drive"] >= split])):
        out[half] = {
            "drives": len(sel),
            "frames_with_match": sum(r["whole_frames_with_match"] for r in sel),
            **{f"{kind}_{key}": pooled(sel, f"whole_{kind}", key)
               for kind in ("causal", "smoothed")
               for key in ("sprint_correct", "accepted_recall_correct")}}
    for kind in ("causal", "smoothed"):
        for key in ("sprint_correct", "accepted_recall_correct"):
            e, lat = out["earlier"][f"{kind}_{key}"], out["later"][f"{kind}_{key}"]
            out[f"later_minus_earlier_{kind}_{key}_points"] = (
                None if e is None or lat is None else round(100 * (lat - e), 2))
    merged = sum(r["merged"] for r in rows)
    out["merged"] = merged
    out["merged_wrong"] = sum(r["merged_wrong"] for r in rows)
    out["merge_precision"] = _ratio(merged - out["merged_wrong"], merged)
    out["unmapped_frames"] = sum(r["unmapped"] for r in rows)
    out["unmapped_merged"] = _ratio(sum(r["unmapped_merged"] for r in rows),
                                    out["unmapped_frames"])
    snap = [r for r in rows if "snapshot_frames_with_match" in r]
    if snap:
        frames = sum(r["snapshot_frames_with_match"] for r in snap)
        before = _ratio(sum(r["snapshot_smoothed_sprint_correct"] for r in snap), frames)
        grown = _ratio(sum(r["grown_on_snapshot_sprint_correct"] for r in snap), frames)
        out["snapshot"] = {"frames": frames, "before_smoothed_recall@1": before,
                           "grown_smoothed_recall@1": grown,
                           "grown_minus_before_points": None if before is None or grown is None
                           else round(100 * (grown - before), 2)}
    return out


def _pct(v: float | None) -> str:
    return "    -" if v is None else f"{100 * v:5.1f}"


def print_rows(label: str, rows: list[dict[str, Any]]) -> None:
    print(f"\n{label}")
    print(f"{'drive':>16} {'cond':>11} {'match':>5} {'hold':>5} | {'kNN@1':>5} {'hkNN':>5} | "
          f"{'caus':>5} {'hold':>5} {'alias':>6} | {'smoo':>5} {'hold':>5} {'alias':>6} | "
          f"{'acc':>5} | {'mrg':>4} {'wrong':>5} {'unmp':>4} {'um-m':>4}")
    for r in rows:
        held = "all" if r["holders_all"] else f"{len(r['holders'])}"
        print(f"{r['name']:>16} {r['condition'][:11]:>11} {r['whole_frames_with_match']:>5} "
              f"{held:>5} | {_pct(r['whole_knn_recall@1'])} {_pct(r['holders_knn_recall@1'])} | "
              f"{_pct(r['whole_causal_sprint_recall@1'])} "
              f"{_pct(r['holders_causal_sprint_recall@1'])} {r['alias_causal_points']:+6.1f} | "
              f"{_pct(r['whole_smoothed_sprint_recall@1'])} "
              f"{_pct(r['holders_smoothed_sprint_recall@1'])} {r['alias_smoothed_points']:+6.1f} | "
              f"{_pct(r['whole_smoothed_accepted_recall@1'])} | {r['merged']:>4} "
              f"{r['merged_wrong']:>5} {r['unmapped']:>4} {r['unmapped_merged']:>4}", flush=True)


def print_summary(label: str, s: dict[str, Any]) -> None:
    def pts(v: float | None) -> str:
        return "-" if v is None else f"{v:+.1f}"

    print(f"  {label}:")
    for kind in ("causal", "smoothed"):
        a = s[f"alias_{kind}"]
        print(f"    alias cost {kind:>8} over {s['aliased_drives']} drives: whole "
              f"{_pct(a['whole_recall@1'])} % vs holders {_pct(a['holders_recall@1'])} % = "
              f"{pts(a['points'])} points (worst drive {pts(a['worst_drive_points'])})")
    e, lat = s["earlier"], s["later"]
    for kind in ("causal", "smoothed"):
        print(f"    {kind:>8}: recall@1 earlier {_pct(e[f'{kind}_sprint_correct'])} % later "
              f"{_pct(lat[f'{kind}_sprint_correct'])} %; accepted recall earlier "
              f"{_pct(e[f'{kind}_accepted_recall_correct'])} % later "
              f"{_pct(lat[f'{kind}_accepted_recall_correct'])} % "
              f"({pts(s[f'later_minus_earlier_{kind}_accepted_recall_correct_points'])} points)")
    print(f"    merges: precision {_pct(s['merge_precision'])} % ({s['merged_wrong']} wrong of "
          f"{s['merged']}), unmapped frames merged {_pct(s['unmapped_merged'])} % of "
          f"{s['unmapped_frames']}")
    if "snapshot" in s:
        snap = s["snapshot"]
        print(f"    snapshot: later half on the {snap['frames']} frames the map before it can "
              f"match: before {_pct(snap['before_smoothed_recall@1'])} %, grown "
              f"{_pct(snap['grown_smoothed_recall@1'])} % "
              f"({pts(snap['grown_minus_before_points'])} points)")


HEADLINE = ("alias_causal.points", "alias_smoothed.points", "alias_causal.worst_drive_points",
            "alias_smoothed.worst_drive_points",
            "later_minus_earlier_smoothed_accepted_recall_correct_points",
            "later_minus_earlier_causal_accepted_recall_correct_points",
            "merge_precision", "unmapped_merged", "snapshot.grown_minus_before_points",
            "earlier.smoothed_accepted_recall_correct", "later.smoothed_accepted_recall_correct")


def headline(summaries: list[dict[str, Any]]) -> dict[str, float | None]:
    """Mean over seeds of the headline figures."""
    out: dict[str, float | None] = {}
    for key in HEADLINE:
        values = []
        for s in summaries:
            v: Any = s
            for part in key.split("."):
                v = v.get(part) if isinstance(v, dict) else None
            if v is not None:
                values.append(float(v))
        out[key] = round(float(np.mean(values)), 4) if values else None
    return out


def parse_arm(text: str) -> tuple[str, list[str]]:
    words = shlex.split(text)
    if not words or "=" in words[0]:
        raise SystemExit(f"--arm: expected 'LABEL KEY=VALUE ...', got {text!r}")
    return words[0], words[1:]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--world", choices=("latent", "city", "nordland"), default="latent")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--drives", type=int, default=None,
                        help="drives per stream (latent/city default 12, nordland 14)")
    parser.add_argument("--frames", type=int, default=None,
                        help="latent/city: frames per drive (default 150); nordland: frames of "
                             "the ride cut (default all)")
    parser.add_argument("--segments", type=int, default=None,
                        help="nordland: segments of the ride (default 24; quick 8)")
    parser.add_argument("--season-strength", type=float, default=None,
                        help="generated worlds: the seasons' strength (default the world's)")
    parser.add_argument("--nordland", type=Path, default=None,
                        help="the Nordland folder (summer/, winter/); default: found as the "
                             "demo finds it")
    parser.add_argument("--quick", action="store_true",
                        help="small streams: ~1 min per seed on 2 cores")
    parser.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                        help="change the map config of every arm (repeatable)")
    parser.add_argument("--arm", dest="arms", action="append", default=[],
                        metavar="'LABEL KEY=VALUE ...'",
                        help="an arm beside the defaults with these changes (repeatable)")
    parser.add_argument("--json", type=Path, help="write rows and summaries here")
    args = parser.parse_args(argv)
    nordland = args.world == "nordland"
    if args.quick:
        args.drives = args.drives or (6 if nordland else 8)
        args.frames = args.frames or (1200 if nordland else 80)
        args.segments = args.segments or 8
    args.drives = args.drives or (14 if nordland else 12)
    args.frames = args.frames or (3576 if nordland else 150)
    args.segments = args.segments or 24
    if args.drives < 3 or args.frames < 10 or args.segments < 4:
        parser.error("need --drives >= 3, --frames >= 10, --segments >= 4")
    arms = [("default", []), *(parse_arm(a) for a in args.arms)]
    started = time.perf_counter()
    results = []
    for seed in args.seeds:
        t0 = time.perf_counter()
        if nordland:
            root = args.nordland or default_nordland()
            if root is None:
                parser.error("Nordland not found: pass --nordland or set $SPRINT_MAP_NORDLAND")
            world = nordland_drives(seed, root, args.frames, args.segments, args.drives)
        elif args.world == "city":
            world = city_world(seed, args.drives, args.frames, args.season_strength)
        else:
            world = latent_world(seed, args.drives, args.frames, args.season_strength)
        print(f"{args.world} seed {seed}: {len(world.drives)} drives, "
              f"{sum(len(d.rows) for d in world.drives)} frames, made in "
              f"{time.perf_counter() - t0:.1f} s", flush=True)
        per_arm = {}
        for label, changes in arms:
            config = apply_sets(apply_sets(world.config, args.sets), changes)
            with tempfile.TemporaryDirectory() as tmp:
                rows = run_stream(world, config, Path(tmp))
            print_rows(f"{args.world} seed {seed}, arm {label}", rows)
            summary = summarise(rows, len(world.drives) // 2)
            print_summary(label, summary)
            per_arm[label] = {"changes": changes, "map_config": config.to_dict(), "rows": rows,
                              "summary": summary}
        results.append({"seed": seed, "world": world.about, "arms": per_arm})
    mean = {label: headline([r["arms"][label]["summary"] for r in results]) for label, _ in arms}
    print(f"\nmean of {len(results)} seed(s):")
    for label, figures in mean.items():
        delta = ""
        if label != "default":
            deltas = []
            for key in HEADLINE:
                mine, base = figures[key], mean["default"][key]
                if mine is not None and base is not None:
                    deltas.append(f"{key} {mine - base:+.4g}")
            delta = "; minus default: " + ", ".join(deltas)
        print(f"  {label}: " + ", ".join(f"{key} {value}" for key, value in figures.items())
              + delta)
    seconds = time.perf_counter() - started
    print(f"{seconds:.0f} s in all")
    if args.json:
        out = {"args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
               "seeds": results, "mean": mean, "seconds": round(seconds, 1)}
        args.json.write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
