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

Held-back *probe* drives (``--probes``; never merged) are answered by the map at the stream's
half and at its end, scored on the frames the map at the half can match: the same frames
answered by two maps, free of what the later drives ask.

Reported per drive: recall@1 (the decision's most probable place is a true match, over the frames
with one), accepted recall (an accepted decision and right), k-NN@1, the alias costs, the merged
decisions and how many are wrong, and the frames of unmapped places (no true match) merged; and
on the *cross-season* frames (those whose places the map holds only under another season, while
it holds the drive's own season elsewhere: the issue's case) recall@1 whole vs holders.
Summary per arm: alias cost pooled over the drives whose holders are not the whole map (and the
worst drive) and over the cross-season frames, accepted recall of the earlier vs the later half
of the stream, merge precision, the share of unmapped frames merged, snapshot and probes
``after - before``; the issue's targets are ``alias >= -2`` points, later >= earlier, merge
precision >= 99 %, unmapped merged <= 1 %.

Worlds (``--world``, built by :mod:`tools.condition_worlds`): ``latent`` and ``city`` (the two
generated families with seasons, :mod:`sprint_map.synth.latent` and
:mod:`sprint_map.synth.seasons`) and ``nordland`` (the real ride cut into ``--segments``
segments; drives of 2-4 consecutive segments, one season each, each with its own exposure and
sensor noise before HoG; true match within +/- 1 frame).

Levers: ``--set KEY=VALUE`` changes the map config of every arm (``MapConfig.replace``: flat keys
such as ``merge_min_run=8`` or ``index_type=flat``; ``part.field=VALUE`` for a field of a part,
e.g. ``hmm.k=20``; values are JSON, else text). ``--arm 'LABEL KEY=VALUE ...'`` adds an arm
with those changes on top, run on the same drives beside the defaults, and the summary gives
each arm minus ``default``.

    python tools/bench_conditions.py --world latent --quick              # ~1 min, 2 cores
    python tools/bench_conditions.py --world city --seeds 0 1 2 --quick
    python tools/bench_conditions.py --world nordland --json nordland-conditions.json
    python tools/bench_conditions.py --world latent --arm 'minrun merge_min_run=8'

``--quick``: latent and city 8 drives x 80 frames (~20-50 s per seed on a loaded 2-core machine);
Nordland the first 900 frames of the ride in 9 segments, 6 drives (~2 min per seed). Cost per drive: up to six localisations of it (k-NN and causal on the
whole map, ingest, causal and smoothed on the holders and on the snapshot) and one map copy;
per probe four. The full Nordland cut (14 drives, ~6,400 frames) takes ~8 min on a loaded 2-core
machine.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map import MapConfig
from sprint_map.evaluation.runner import QueryResult, evaluate_query
from sprint_map.frontend import GroundTruth
from sprint_map.localize.localizer import FrameDecision
from sprint_map.map import SprintMap

if __package__ in (None, ""):  # run as ``python tools/...``: ``tools`` from the checkout
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tools.bench_lifelong import score  # noqa: E402
from tools.condition_worlds import (  # noqa: E402
    Drive,
    World,
    city_world,
    default_nordland,
    latent_world,
    nordland_world,
)

KS = (1, 10)


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


def _names(m: SprintMap) -> dict[int, str]:
    return {s.seq_id: s.name for s in m.sequences()}


def causal_answer(m: SprintMap, drive: Drive, gt: GroundTruth
                  ) -> tuple[QueryResult, list[FrameDecision], dict[int, str]]:
    """The drive answered by ``m`` by exact k-NN and causally (streamed), read-only."""
    knn, causal = evaluate_query(m, drive.name, drive.rows, gt, KS, None)
    return knn, causal, _names(m)


def scored(knn: QueryResult, causal: list[FrameDecision], smoothed: list[FrameDecision],
           drive: Drive, gt: GroundTruth, names: dict[int, str], prefix: str) -> dict[str, Any]:
    """k-NN, causal and smoothed answers of one map, scored over the frames with a true match
    in it; keys prefixed ``prefix_``."""
    has = knn.has_match
    out: dict[str, Any] = {f"{prefix}_frames_with_match": int(has.sum())}
    for k in KS:
        hits = knn.knn_correct[:, :k].any(axis=1) & has
        out[f"{prefix}_knn_recall@{k}"] = round(float(hits.sum()) / max(int(has.sum()), 1), 4)
    out.update(_decisions_score(causal, drive, gt, names, has, f"{prefix}_causal"))
    out.update(_decisions_score(smoothed, drive, gt, names, has, f"{prefix}_smoothed"))
    return out


def answer(m: SprintMap, drive: Drive, gt: GroundTruth, prefix: str
           ) -> tuple[dict[str, Any], list[FrameDecision], list[FrameDecision]]:
    """The drive answered by ``m``, read-only: k-NN, causal, and smoothed as ``localize
    --smooth`` (what ``ingest`` would merge); the scores and both decision lists."""
    knn, causal, names = causal_answer(m, drive, gt)
    smoothed, _ = m.localize(drive.rows, smooth=True)
    return scored(knn, causal, smoothed, drive, gt, names, prefix), causal, smoothed


def on_frames(m: SprintMap, drive: Drive, gt: GroundTruth, decisions: dict[str, list[FrameDecision]],
              names: dict[int, str], prefix: str) -> dict[str, Any]:
    """``decisions`` (by kind: causal, smoothed) made against a map of ``names``, scored on the
    frames ``m`` can match (another map's frames: the same frames answered by two maps)."""
    has = gt.has_match(drive.name, np.arange(len(drive.rows)), list(_names(m).values()))
    out: dict[str, Any] = {f"{prefix}_frames_with_match": int(has.sum())}
    for kind, made in decisions.items():
        out.update(_decisions_score(made, drive, gt, names, has, f"{prefix}_{kind}"))
    return out


def cross_season(drive: Drive, earlier: list[Drive], gt: GroundTruth) -> np.ndarray:
    """Per frame of ``drive``: it has a true match among the ``earlier`` drives of another
    season, none among those of its own, and some earlier drive is of its own season (so the
    map holds that season elsewhere)."""
    frames = np.arange(len(drive.rows))
    same = [d.name for d in earlier if d.season == drive.season]
    other = [d.name for d in earlier if d.season != drive.season]
    if not same or not other:
        return np.zeros(len(frames), dtype=bool)
    cross: np.ndarray = gt.has_match(drive.name, frames, other) & ~gt.has_match(
        drive.name, frames, same)
    return cross


def _copy(m: SprintMap, path: Path, target: Path) -> SprintMap:
    """Close ``m``, copy its map to ``target`` and reopen it (a map is copied closed)."""
    m.close()
    shutil.copytree(path, target)
    return SprintMap.open(path)


def run_stream(world: World, config: MapConfig, work: Path,
               on_row: Callable[[dict[str, Any]], None] | None = None
               ) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Merge the world's drives in turn into a fresh map: one row per drive after the first
    (each also given to ``on_row`` as soon as it is made), and one per probe (held back:
    answered by the map at the half and at the end)."""
    drives, gt = world.drives, world.gt
    split = len(drives) // 2
    path, snap_path, hold_path = work / "map", work / "snapshot", work / "holders"
    snapshot: SprintMap | None = None
    rows: list[dict[str, Any]] = []
    m = SprintMap.create(path, config)
    try:
        for i, drive in enumerate(drives):
            if i == split:
                m = _copy(m, path, snap_path)
                snapshot = SprintMap.open(snap_path, readonly=True)
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
            aliased = bool(holders) and not row["holders_all"]
            if aliased:  # the map before this drive, less the drives of other places
                m = _copy(m, path, hold_path)
            knn, causal, names = causal_answer(m, drive, gt)
            # The whole map's smoothed answers are ingest's own decisions (those it merges).
            result = m.ingest(drive.rows, name=drive.name, merge=True)
            smoothed = result.decisions
            row.update(scored(knn, causal, smoothed, drive, gt, names, "whole"))
            held_names, held_causal, held_smoothed = names, causal, smoothed
            if aliased:
                try:
                    with SprintMap.open(hold_path) as held:
                        held.remove_sequences([n for n in earlier if n not in holders])
                        held_names = _names(held)
                        scores, held_causal, held_smoothed = answer(held, drive, gt, "holders")
                        row.update(scores)
                finally:
                    shutil.rmtree(hold_path)
            else:
                row.update({key.replace("whole_", "holders_", 1): value
                            for key, value in row.items() if key.startswith("whole_")})
            # Frames whose places the map holds only under another season while it holds the
            # drive's own season elsewhere: the issue's case of condition aliasing.
            cross = cross_season(drive, drives[:i], gt)
            row["cross_frames"] = int(cross.sum())
            for prefix, nm, made in (("whole", names, (causal, smoothed)),
                                     ("holders", held_names, (held_causal, held_smoothed))):
                for kind, decisions in zip(("causal", "smoothed"), made, strict=True):
                    row[f"{prefix}_cross_{kind}_sprint_correct"] = score(
                        decisions, drive.name, gt, nm, cross)["sprint_correct"]
            for kind in ("causal", "smoothed"):
                row[f"alias_{kind}_points"] = round(100 * (
                    row[f"whole_{kind}_sprint_recall@1"]
                    - row[f"holders_{kind}_sprint_recall@1"]), 2)
            if snapshot is not None:  # the same frames, by the map before the later half
                row.update(answer(snapshot, drive, gt, "snapshot")[0])
                row.update(on_frames(snapshot, drive, gt, {"causal": causal,
                                                           "smoothed": smoothed},
                                     names, "grown_on_snapshot"))
            has = knn.has_match
            merged = np.asarray(result.merged, dtype=bool)
            if not len(merged):
                merged = np.zeros(len(frames), dtype=bool)
            right = np.array([d.seq_id is not None and d.image_id is not None and bool(
                gt.correct(drive.name, d.frame, names[d.seq_id], d.image_id))
                for d in smoothed], dtype=bool)
            row.update(merged=int(merged.sum()), merged_wrong=int((merged & ~(right & has)).sum()),
                       unmapped=int((~has).sum()), unmapped_merged=int((merged & ~has).sum()),
                       edges_added=result.edges_added,
                       seconds=round(time.perf_counter() - start, 2))
            rows.append(row)
            if on_row is not None:
                on_row(row)
        probes = run_probes(world, snapshot, m) if snapshot is not None else []
    finally:
        m.close()
        if snapshot is not None:
            snapshot.close()
    return rows, probes


def run_probes(world: World, before: SprintMap, after: SprintMap) -> list[dict[str, Any]]:
    """Each probe answered by the map at the stream's half (``before``) and at its end
    (``after``), both scored on the frames ``before`` can match (``after_on_before_*``): what
    the later half of the stream did to the same held-back frames."""
    out = []
    for probe in world.probes:
        row: dict[str, Any] = {"name": probe.name, "season": probe.season,
                               "condition": probe.condition, "frames": len(probe.rows)}
        scores, _, _ = answer(before, probe, world.gt, "before")
        row.update(scores)
        scores, causal, smoothed = answer(after, probe, world.gt, "after")
        row.update(scores)
        row.update(on_frames(before, probe, world.gt, {"causal": causal, "smoothed": smoothed},
                             _names(after), "after_on_before"))
        for kind in ("causal", "smoothed"):
            row[f"after_minus_before_{kind}_points"] = round(100 * (
                row[f"after_on_before_{kind}_sprint_recall@1"]
                - row[f"before_{kind}_sprint_recall@1"]), 2)
        out.append(row)
    return out


def _ratio(num: float, den: float) -> float | None:
    return round(num / den, 4) if den else None


def summarise(rows: list[dict[str, Any]], split: int, probes: list[dict[str, Any]]
              ) -> dict[str, Any]:
    """Pooled figures of one arm's rows (``split``: first drive of the later half) and probes."""
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
    cross = sum(r["cross_frames"] for r in rows)
    out["cross_season"] = {"frames": cross, "drives": sum(r["cross_frames"] > 0 for r in rows)}
    for kind in ("causal", "smoothed"):
        whole = _ratio(sum(r[f"whole_cross_{kind}_sprint_correct"] for r in rows), cross)
        held = _ratio(sum(r[f"holders_cross_{kind}_sprint_correct"] for r in rows), cross)
        out["cross_season"][kind] = {
            "whole_recall@1": whole, "holders_recall@1": held,
            "points": None if whole is None or held is None else round(100 * (whole - held), 2)}
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
        out["snapshot"] = same_frames(snap, "snapshot", "grown_on_snapshot")
    if probes:
        out["probes"] = same_frames(probes, "before", "after_on_before")
    return out


def same_frames(rows: list[dict[str, Any]], first: str, second: str) -> dict[str, Any]:
    """Pooled recall@1 of the same frames answered by two maps (keys ``first_*`` and
    ``second_*`` of ``rows``, over ``first``'s frames with a match), causal and smoothed."""
    frames = sum(r[f"{first}_frames_with_match"] for r in rows)
    out: dict[str, Any] = {"drives": len(rows), "frames": frames}
    for kind in ("causal", "smoothed"):
        one = _ratio(sum(r[f"{first}_{kind}_sprint_correct"] for r in rows), frames)
        two = _ratio(sum(r[f"{second}_{kind}_sprint_correct"] for r in rows), frames)
        out[kind] = {"before_recall@1": one, "after_recall@1": two,
                     "points": None if one is None or two is None else round(100 * (two - one), 2)}
    return out


def _pct(v: float | None) -> str:
    return "    -" if v is None else f"{100 * v:5.1f}"


def print_header(label: str) -> None:
    print(f"\n{label}")
    print(f"{'drive':>16} {'cond':>11} {'match':>5} {'hold':>5} | {'kNN@1':>5} {'hkNN':>5} | "
          f"{'caus':>5} {'hold':>5} {'alias':>6} | {'smoo':>5} {'hold':>5} {'alias':>6} | "
          f"{'acc':>5} | {'mrg':>4} {'wrong':>5} {'unmp':>4} {'um-m':>4}", flush=True)


def print_row(r: dict[str, Any]) -> None:
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
    c = s["cross_season"]
    print(f"    cross-season frames ({c['frames']} in {c['drives']} drives: held only under the "
          "other season, the drive's season held elsewhere): " + "; ".join(
              f"{kind} whole {_pct(c[kind]['whole_recall@1'])} % vs holders "
              f"{_pct(c[kind]['holders_recall@1'])} % ({pts(c[kind]['points'])})"
              for kind in ("causal", "smoothed")))
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
    for key, what, before, after in (
            ("snapshot", "later-half drives", "map before the later half", "grown map"),
            ("probes", "held-back probes", "map at the half", "map at the end")):
        if key in s:
            same = s[key]
            print(f"    {key}: {same['drives']} {what} on the {same['frames']} frames the "
                  f"{before} can match, {before} vs {after}: " + "; ".join(
                      f"{kind} {_pct(same[kind]['before_recall@1'])} -> "
                      f"{_pct(same[kind]['after_recall@1'])} % "
                      f"({pts(same[kind]['points'])})" for kind in ("causal", "smoothed")))


def print_probes(rows: list[dict[str, Any]]) -> None:
    if not rows:
        return
    print(f"  {'probe':>16} {'cond':>11} | {'match@half':>10} {'caus':>5} {'smoo':>5} | "
          f"{'match@end':>9} {'caus':>5} {'smoo':>5} | {'same frames: caus':>17} {'smoo':>5}")
    for r in rows:
        print(f"  {r['name']:>16} {r['condition'][:11]:>11} | {r['before_frames_with_match']:>10} "
              f"{_pct(r['before_causal_sprint_recall@1'])} "
              f"{_pct(r['before_smoothed_sprint_recall@1'])} | "
              f"{r['after_frames_with_match']:>9} {_pct(r['after_causal_sprint_recall@1'])} "
              f"{_pct(r['after_smoothed_sprint_recall@1'])} | "
              f"{r['after_minus_before_causal_points']:+17.1f} "
              f"{r['after_minus_before_smoothed_points']:+5.1f}")


HEADLINE = ("alias_causal.points", "alias_smoothed.points", "alias_causal.worst_drive_points",
            "alias_smoothed.worst_drive_points", "cross_season.causal.points",
            "cross_season.smoothed.points",
            "later_minus_earlier_smoothed_accepted_recall_correct_points",
            "later_minus_earlier_causal_accepted_recall_correct_points",
            "merge_precision", "unmapped_merged", "snapshot.causal.points",
            "snapshot.smoothed.points", "probes.causal.points", "probes.smoothed.points",
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
    """``'LABEL KEY=VALUE ...'`` -> ``(LABEL, ['KEY=VALUE', ...])``. A value runs to the next
    ``KEY=``, so JSON keeps its quotes and spaces (``centring={"mode": "drive"}``)."""
    label, _, rest = text.strip().partition(" ")
    if not label or "=" in label:
        raise SystemExit(f"--arm: expected 'LABEL KEY=VALUE ...', got {text!r}")
    words = re.split(r"\s+(?=[A-Za-z_][\w.]*=)", rest.strip()) if rest.strip() else []
    if any("=" not in word for word in words):
        raise SystemExit(f"--arm: expected 'LABEL KEY=VALUE ...', got {text!r}")
    return label, words


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
                        help="nordland: segments of the ride (default 24; quick 9)")
    parser.add_argument("--probes", type=int, default=None,
                        help="held-back drives answered at the half and the end, never merged "
                             "(default: generated worlds 4, one cycle of seasons; nordland 2)")
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
        args.frames = args.frames or (900 if nordland else 80)
        args.segments = args.segments or 9
    args.drives = args.drives or (14 if nordland else 12)
    args.frames = args.frames or (3576 if nordland else 150)
    args.segments = args.segments or 24
    args.probes = (2 if nordland else 4) if args.probes is None else args.probes
    if args.drives < 3 or args.frames < 10 or args.segments < 4:
        parser.error("need --drives >= 3, --frames >= 10, --segments >= 4")
    if args.probes < 0:
        parser.error("need --probes >= 0")
    arms = [("default", []), *(parse_arm(a) for a in args.arms)]
    started = time.perf_counter()
    results = []
    for seed in args.seeds:
        t0 = time.perf_counter()
        if nordland:
            root = args.nordland or default_nordland()
            if root is None:
                parser.error("Nordland not found: pass --nordland or set $SPRINT_MAP_NORDLAND")
            world = nordland_world(seed, root, args.frames, args.segments, args.drives,
                                   args.probes)
        elif args.world == "city":
            world = city_world(seed, args.drives, args.frames, args.season_strength, args.probes)
        else:
            world = latent_world(seed, args.drives, args.frames, args.season_strength,
                                 args.probes)
        print(f"{args.world} seed {seed}: {len(world.drives)} drives, "
              f"{sum(len(d.rows) for d in world.drives)} frames, made in "
              f"{time.perf_counter() - t0:.1f} s", flush=True)
        per_arm = {}
        for label, changes in arms:
            config = apply_sets(apply_sets(world.config, args.sets), changes)
            with tempfile.TemporaryDirectory() as tmp:
                print_header(f"{args.world} seed {seed}, arm {label}")
                rows, probes = run_stream(world, config, Path(tmp), print_row)
            print_probes(probes)
            summary = summarise(rows, len(world.drives) // 2, probes)
            print_summary(label, summary)
            per_arm[label] = {"changes": changes, "map_config": config.to_dict(), "rows": rows,
                              "probes": probes, "summary": summary}
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
