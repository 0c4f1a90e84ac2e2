"""Lifelong: does the map get better as it grows?

A synthetic city (:mod:`sprint_map.synth`: rendered images described by HoG, as the demo does) is
driven ``--traversals`` times (default 24) over the same few streets, the conditions in turn
(traversal ``i`` under ``CONDITIONS[i % 4]``: day, dusk, rain, snow). The lifelong protocol runs
twice on the same descriptors, each on its own map:

- ``merge`` (the product): ``SprintMap.ingest(rows, merge=True)`` localises each drive against
  the map of all earlier ones, then commits it with its confident decisions as edges;
- ``no-merge``: each drive is localised against the map as it stands, read-only, as ingest
  would (``SprintMap.localize(rows, smooth=True)``), then appended with
  ``ingest(merge=False)``: no edges, every drive its own component.

Per traversal after the first: SPRINT recall@1 (each decision's most probable place, ``best``,
is a true match by the data set's ground truth: within ``radius_m`` and ``heading_deg``), over
the frames that have a true match; the recall@1 of *accepted* decisions (``is_match`` and a true
match, over the frames that have one: what issue 13 measured when the map degraded as it grew,
a split belief then being answered "no match"); the precision of the accepted decisions (``is_match``,
counted over every accepted frame, with or without a true match); exact k-NN recall@1 and @10
(the same map contents in both runs, so the same numbers); in the merge run, the decisions
merged as edges (``merged``) and how many of them are wrong by the ground truth
(``merged_wrong``, the table's ``wrongM``; ``merge_precision`` per half): a wrong edge stays in
the map for every later drive. Summary per run: recall@1 pooled over
the earlier half of the traversals (1 .. N/2 - 1) and over the later half (N/2 .. N - 1), and
merge minus no-merge on the later half, in points.

The two halves are different frames: early drives can only be scored where the small map
reaches, later drives everywhere, so "later minus earlier" mixes the map's growth with what the
drives ask. The *snapshot* control separates them: each later-half drive is also localised
against a copy of the map as it stood before the later half, and both answers are scored on the
frames that copy can match ("grown - before", per run).

Which decisions: ``merge`` scores ``IngestResult.decisions``, the ones the merge used (made
from the smoothed posterior once the drive has been seen); ``no-merge``, whose ingest localises
nothing, scores ``SprintMap.localize(rows, smooth=True)``, documented as the same decisions.
``ingest_differs_from_localize`` counts, in the merge run, the frames where the two disagree
(they are compared on the same map before each commit; 0 is expected). ``online_*`` scores the
causal frame-by-frame decisions a vehicle gets while driving (a streaming localizer), in both
runs.

    python tools/bench_lifelong.py --json lifelong.json --png lifelong.png   # ~4 min, 2 cores
    python tools/bench_lifelong.py --seeds 0 --traversals 32 --frames 200
    python tools/bench_lifelong.py --quick            # 8 traversals x 60 frames, a smoke run
    python tools/bench_lifelong.py --world hard --frames 150   # 4 x 4 grid, one facade style

Every drive keeps its thumbnails (as ``ingest --thumbnails`` does), so the merge verifies on the
images the runs its lookalike tests refuse (:mod:`sprint_map.merge.verification`); both runs localise
the same way. ``--no-thumbnails`` measures without them.

``--world hard`` drives a 4 x 4 grid with one facade style under dusk / rain / fog / snow in
turn: exact k-NN@1 is ~70 % instead of ~85 %, so belief split over parallel drives matters more.

``--world latent`` is the other world family (:mod:`sprint_map.synth.latent`, preset
``latent-lifelong``): descriptor-level drives over latent places on a 4 x 4 street network,
lookalike streets and one identical twin, its six conditions in turn, each drive after the
first aiming at 20 % of its frames on streets the map has not seen; exact k-NN@1 ~36 %, @10
~75 %. Its drives have no images, so no thumbnails (the merge verifies nothing on images).

    python tools/bench_lifelong.py --world latent --json lifelong-latent.json   # ~3 min/seed

``--admission`` adds an arm ``merge+novel``: the merge run on a map created with
``admission="novel"`` (:mod:`sprint_map.merge.admission`: a drive stores only what the map does
not hold). Per drive it reports the frames stored, the map's vertices and disk bytes, and the
per-frame cost (retrieval + HMM); the summary gives the map's size in traversals' worth of
frames, its growth over the last fifth of the drives, and novel minus merge on the later half
(recall@1 and merge precision). The ground truth of a stored stretch is its frames' positions.

    python tools/bench_lifelong.py --world latent --traversals 100 --admission --png grow.png
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map import MapConfig
from sprint_map.evaluation.runner import evaluate_query
from sprint_map.frontend import GroundTruth
from sprint_map.frontend.thumbnails import make_thumbnail
from sprint_map.localize.localizer import FrameDecision
from sprint_map.map import SprintMap
from sprint_map.merge.commit import IngestResult
from sprint_map.synth import CityConfig, iter_city
from sprint_map.synth.latent import LATENT_PRESETS, LatentConfig, make_latent

#: Conditions in turn: traversal i is driven under CONDITIONS[i % 4].
CONDITIONS = ("day", "dusk", "rain", "snow")
#: A 3 x 3 grid (12 streets) and a strong preference for driven streets: after the first few
#: traversals nearly every frame is on a street the map has seen in the same direction.
CITY = CityConfig(grid=(3, 3), revisit=1000.0, conditions=CONDITIONS)
#: ``--world hard``: harsher conditions in turn, one facade style (every street looks alike) and
#: a larger grid: exact k-NN@1 is far lower, so belief split over parallel drives matters.
HARD_CONDITIONS = ("dusk", "rain", "fog", "snow")
WORLDS = {
    "easy": CITY,
    "hard": CityConfig(grid=(4, 4), revisit=1000.0, conditions=HARD_CONDITIONS, n_styles=1),
}
#: ``--world latent``: the descriptor-level family.
LATENT = LATENT_PRESETS["latent-lifelong"]
KS = (1, 10)
ARMS = ("merge", "no-merge")
#: ``--admission``: the merge run on a map that stores only what it lacks.
NOVEL_ARM = "merge+novel"


@dataclasses.dataclass
class Drive:
    """One traversal as the benchmark uses it: descriptors and planar positions."""

    name: str
    condition: str
    rows: np.ndarray  # (N, dim) float32 HoG
    xy: np.ndarray  # (N, 2)
    thumbnails: list[bytes] | None  # one JPEG per frame, as ``ingest --thumbnails`` keeps them
    positions: np.ndarray  # (N, 3 or 4): the ground truth's ``frame, x, y[, heading_deg]``


def render_drives(seed: int, traversals: int, frames: int, config: CityConfig,
                  workers: int | None, thumbnails: bool = True
                  ) -> tuple[list[Drive], GroundTruth, float]:
    """Render the city traversal by traversal, keeping only descriptors, positions and (with
    ``thumbnails``) a thumbnail of each frame.

    Returns the drives, their ground truth and the seconds spent.
    """
    start = time.perf_counter()
    spec = MapConfig.for_descriptor("hog").descriptor_spec()
    assert spec is not None
    drives, positions = [], {}
    for traversal in iter_city(traversals, frames, seed=seed, config=config, workers=workers):
        rows = spec.describe_batch(traversal.images)
        thumbs = [make_thumbnail(image) for image in traversal.images] if thumbnails else None
        drives.append(Drive(traversal.name, traversal.condition, rows,
                            traversal.positions[:, 1:3].copy(), thumbs, traversal.positions))
        positions[traversal.name] = traversal.positions
    gt = GroundTruth(config.ground_truth_spec(), positions=positions)
    return drives, gt, time.perf_counter() - start


def latent_drives(seed: int, traversals: int, frames: int, config: LatentConfig
                  ) -> tuple[list[Drive], GroundTruth, float]:
    """The latent world's drives (descriptors and positions; no images, so no thumbnails)."""
    start = time.perf_counter()
    world = make_latent(traversals, frames, seed, config)
    drives = [Drive(t.name, t.condition, t.descriptors, t.positions[:, 1:3].copy(), None,
                    t.positions) for t in world.traversals]
    return drives, world.ground_truth(), time.perf_counter() - start


def score(decisions: list[FrameDecision], query: str, gt: GroundTruth, names: dict[int, str],
          has_match: np.ndarray) -> dict[str, Any]:
    """SPRINT recall@1 and the precision of accepted decisions, by the ground truth."""
    best_correct = np.zeros(len(has_match), dtype=bool)
    accepted = np.zeros(len(has_match), dtype=bool)
    accepted_correct = np.zeros(len(has_match), dtype=bool)
    for d in decisions:
        if d.best is not None:
            seq_id, image_id = d.best
            best_correct[d.frame] = bool(gt.correct(query, d.frame, names[seq_id], image_id))
        if d.is_match:
            assert d.seq_id is not None and d.image_id is not None
            accepted[d.frame] = True
            accepted_correct[d.frame] = bool(
                gt.correct(query, d.frame, names[d.seq_id], d.image_id))
    matchable = int(has_match.sum())
    return {
        "sprint_correct": int((best_correct & has_match).sum()),
        "sprint_recall@1": round(float((best_correct & has_match).sum()) / max(matchable, 1), 4),
        "accepted": int(accepted.sum()),
        "accepted_correct": int(accepted_correct.sum()),
        "accepted_recall_correct": int((accepted_correct & has_match).sum()),
        "accepted_recall@1": round(float((accepted_correct & has_match).sum())
                                   / max(matchable, 1), 4),
        "precision": (round(float(accepted_correct.sum()) / int(accepted.sum()), 4)
                      if accepted.any() else None),
    }


def run_arm(drives: list[Drive], gt: GroundTruth, merge: bool, work: Path,
            config: MapConfig | None = None, learn_every: int = 0) -> list[dict[str, Any]]:
    """See :func:`run_arm_on`; a map with admission ``novel`` gets a ground truth of its own,
    where each stored sequence has the positions of the frames it stored."""
    config = config or MapConfig.for_descriptor("hog")
    if config.admission.mode == "all":
        return run_arm_on(drives, gt, merge, work, config, learn_every)
    positions = {d.name: d.positions for d in drives}
    stored_gt = GroundTruth(gt.spec, positions=positions)

    def stored(drive: Drive, result: IngestResult) -> None:
        if result.frames_stored < len(drive.rows):
            table = drive.positions[result.image_of >= 0].copy()
            table[:, 0] = np.arange(len(table))
            positions[drive.name] = table

    rows = run_arm_on(drives, stored_gt, merge, work, config, learn_every, stored)
    path = work / f"{arm_name(merge, learn_every, config)}.map"
    rows[-1]["reingest_stored_earlier"] = {
        drives[i].name: reingest_stored(path, drives[i], copy=True)
        for i in sorted({len(drives) // 4, len(drives) // 2, 3 * len(drives) // 4})}
    rows[-1]["reingest_stored"] = reingest_stored(path, drives[-1])
    return rows


def arm_name(merge: bool, learn_every: int, config: MapConfig) -> str:
    """The name of an arm's map: ``merge`` or ``no-merge``, then ``-learn`` and ``-novel``
    as it learns and admits."""
    return (("merge" if merge else "no-merge") + ("-learn" if learn_every else "")
            + ("-novel" if config.admission.mode != "all" else ""))


def reingest_stored(path: Path, drive: Drive, noise: float = 0.01, copy: bool = False) -> int:
    """Frames stored when ``drive``, already in the map at ``path``, is ingested again with
    Gaussian noise of ``noise`` times its descriptors' spread (``copy``: into a copy of the
    map, deleted after)."""
    rng = np.random.default_rng(0)
    again = drive.rows + rng.normal(0, noise * float(drive.rows.std()), drive.rows.shape)
    target = path.with_name(path.name + "-again") if copy else path
    if copy:
        shutil.copytree(path, target)
    try:
        with SprintMap.open(target) as m:
            return m.ingest(again.astype(np.float32), name=drive.name + "-again",
                            positions=drive.xy, thumbnails=drive.thumbnails).frames_stored
    finally:
        if copy:
            shutil.rmtree(target)


def run_arm_on(drives: list[Drive], gt: GroundTruth, merge: bool, work: Path,
               config: MapConfig, learn_every: int = 0,
               on_stored: Callable[[Drive, IngestResult], None] | None = None
               ) -> list[dict[str, Any]]:
    """The lifelong protocol on one fresh map (default config: HoG); one row per traversal
    after the first. ``learn_every`` > 0: the map learns its descriptor (``index --learn``)
    after every ``learn_every`` drives. Each later-half drive is also localised against a copy
    of the map as it stood before the later half (the *snapshot*), and both maps' answers are
    scored on the frames the snapshot can match (``snapshot_*`` keys of the rows)."""
    rows_out: list[dict[str, Any]] = []
    name = arm_name(merge, learn_every, config)
    split = len(drives) // 2  # the first traversal of the later half (as summarise splits)
    path = work / f"{name}.map"
    snapshot: SprintMap | None = None
    m = SprintMap.create(path, config)
    try:
        for i, drive in enumerate(drives):
            if i == split:
                m.close()
                shutil.copytree(path, work / f"{name}-snapshot.map")
                snapshot = SprintMap.open(work / f"{name}-snapshot.map", readonly=True)
                m = SprintMap.open(path)
            learned = None
            if learn_every and i and i % learn_every == 0:
                learned = m.learn()
            if i == 0:
                m.ingest(drive.rows, name=drive.name, positions=drive.xy, merge=merge,
                         thumbnails=drive.thumbnails)
                continue
            start = time.perf_counter()
            names = {s.seq_id: s.name for s in m.sequences()}
            vertices = m.stats()["vertices"]
            # Exact k-NN, the ground truth's matchable frames and the streaming decisions, then
            # ingest's own decisions read-only, all on the map before this drive.
            knn, streamed = evaluate_query(m, drive.name, drive.rows, gt, KS, None)
            offline, _ = m.localize(drive.rows, smooth=True, thumbnails=drive.thumbnails)
            result = m.ingest(drive.rows, name=drive.name, positions=drive.xy, merge=merge,
                              thumbnails=drive.thumbnails)
            decisions = result.decisions if merge else offline
            matchable = int(knn.has_match.sum())
            online = score(streamed, drive.name, gt, names, knn.has_match)
            row: dict[str, Any] = {
                "traversal": i,
                "name": drive.name,
                "condition": drive.condition,
                "frames": len(drive.rows),
                "frames_with_match": matchable,
                "map_vertices": vertices,
                **score(decisions, drive.name, gt, names, knn.has_match),
                **{f"online_{key}": value for key, value in online.items()},
            }
            for k in KS:
                hits = knn.knn_correct[:, :k].any(axis=1) & knn.has_match
                row[f"knn_correct@{k}"] = int(hits.sum())
                row[f"knn_recall@{k}"] = round(float(hits.sum()) / max(matchable, 1), 4)
            if merge:
                row["ingest_differs_from_localize"] = sum(
                    (a.best, a.seq_id, a.image_id) != (b.best, b.seq_id, b.image_id)
                    for a, b in zip(result.decisions, offline, strict=True))
            merged = [d for d, keep in zip(result.decisions, np.asarray(result.merged).tolist(),
                                           strict=True) if keep and merge]
            row["merged"] = len(merged)
            row["merged_wrong"] = sum(
                d.seq_id is None or d.image_id is None
                or not gt.correct(drive.name, d.frame, names[d.seq_id], d.image_id)
                for d in merged)
            if learned is not None:
                row["learned"] = learned
            if snapshot is not None:
                row.update(snapshot_scores(snapshot, drive, gt, decisions, names))
            stats = m.stats()
            timing = result.timing.to_dict()
            row.update(edges_added=result.edges_added, components=stats["components"],
                       frames_stored=result.frames_stored, map_vertices_after=stats["vertices"],
                       disk_bytes=m.store.disk_bytes(),
                       frame_ms=round(timing["retrieval_ms_per_frame"]
                                      + timing["hmm_ms_per_frame"], 4),
                       seconds=round(time.perf_counter() - start, 2))
            rows_out.append(row)
            if on_stored is not None:  # scored as a query: from now on a stored stretch
                on_stored(drive, result)
    finally:
        m.close()
        if snapshot is not None:
            snapshot.close()
    return rows_out


def snapshot_scores(snapshot: SprintMap, drive: Drive, gt: GroundTruth,
                    decisions: list[FrameDecision], names: dict[int, str]) -> dict[str, int]:
    """The drive localised against the ``snapshot`` (smoothed, as ingest decides) and the grown
    map's ``decisions`` (against ``names``), both scored on the frames the snapshot can match:
    what the map's growth alone changed, on the same frames."""
    snap_names = {s.seq_id: s.name for s in snapshot.sequences()}
    frames = np.arange(len(drive.rows))
    has_match = gt.has_match(drive.name, frames, list(snap_names.values()))
    snap, _ = snapshot.localize(drive.rows, smooth=True, thumbnails=drive.thumbnails)
    return {"snapshot_frames_with_match": int(has_match.sum()),
            "snapshot_sprint_correct": score(snap, drive.name, gt, snap_names,
                                             has_match)["sprint_correct"],
            "grown_sprint_correct_on_snapshot_frames": score(
                decisions, drive.name, gt, names, has_match)["sprint_correct"]}


def pooled(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Recalls over all frames with a match of ``rows``, precision over all accepted."""
    matchable = sum(r["frames_with_match"] for r in rows)
    accepted = sum(r["accepted"] for r in rows)
    out: dict[str, Any] = {
        "traversals": [r["traversal"] for r in rows][:1] + [r["traversal"] for r in rows][-1:],
        "frames_with_match": matchable,
        "sprint_recall@1": round(sum(r["sprint_correct"] for r in rows) / max(matchable, 1), 4),
        "precision": (round(sum(r["accepted_correct"] for r in rows) / accepted, 4)
                      if accepted else None),
        "accepted": accepted,
        "accepted_recall@1": round(sum(r["accepted_recall_correct"] for r in rows)
                                   / max(matchable, 1), 4),
    }
    merged = sum(r.get("merged", 0) for r in rows)
    out["merged"] = merged
    out["merged_wrong"] = sum(r.get("merged_wrong", 0) for r in rows)
    out["merge_precision"] = (round(1 - out["merged_wrong"] / merged, 4) if merged else None)
    out["online_sprint_recall@1"] = round(sum(r["online_sprint_correct"] for r in rows)
                                          / max(matchable, 1), 4)
    out["online_accepted_recall@1"] = round(sum(r["online_accepted_recall_correct"]
                                                for r in rows) / max(matchable, 1), 4)
    for k in KS:
        out[f"knn_recall@{k}"] = round(sum(r[f"knn_correct@{k}"] for r in rows)
                                       / max(matchable, 1), 4)
    return out


def snapshot_summary(later: list[dict[str, Any]]) -> dict[str, Any] | None:
    """The later half against the map before it (the snapshot) and against the grown map, on
    the same frames (those the snapshot can match): recall@1 of each and grown minus snapshot
    in points. None without snapshot rows."""
    rows = [r for r in later if "snapshot_frames_with_match" in r]
    frames = sum(r["snapshot_frames_with_match"] for r in rows)
    if not frames:
        return None
    snap = sum(r["snapshot_sprint_correct"] for r in rows) / frames
    grown = sum(r["grown_sprint_correct_on_snapshot_frames"] for r in rows) / frames
    return {"frames": frames, "snapshot_recall@1": round(snap, 4),
            "grown_recall@1": round(grown, 4),
            "grown_minus_snapshot_points": round(100 * (grown - snap), 2)}


def summarise(arms: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    """Earlier half vs later half per arm, and merge vs no-merge on the later half."""
    out: dict[str, Any] = {}
    for arm, rows in arms.items():
        split = (len(rows) + 1) // 2  # N traversals: 1 .. N/2 - 1 vs N/2 .. N - 1
        earlier = [r for r in rows if r["traversal"] < split]
        later = [r for r in rows if r["traversal"] >= split]
        e, lat = pooled(earlier), pooled(later)
        out[arm] = {"earlier": e, "later": lat,
                    "later_minus_earlier_points": round(
                        100 * (lat["sprint_recall@1"] - e["sprint_recall@1"]), 2),
                    "accepted_later_minus_earlier_points": round(
                        100 * (lat["accepted_recall@1"] - e["accepted_recall@1"]), 2),
                    "snapshot": snapshot_summary(later)}
    for key, prefix in (("sprint_recall@1", ""), ("online_sprint_recall@1", "online_"),
                        ("accepted_recall@1", "accepted_"),
                        ("online_accepted_recall@1", "online_accepted_")):
        out[f"{prefix}merge_minus_no_merge_later_points"] = round(
            100 * (out["merge"]["later"][key] - out["no-merge"]["later"][key]), 2)
    if "merge+learn" in arms:
        out["learn_minus_merge_later_points"] = {key: round(100 * (
            out["merge+learn"]["later"][key] - out["merge"]["later"][key]), 2) for key in (
            "sprint_recall@1", "online_sprint_recall@1", "knn_recall@1")}
        reports = [r["learned"] for r in arms["merge+learn"] if "learned" in r]
        out["learn_adopted"] = {"tried": len(reports),
                                "adopted": sum(bool(r["adopted"]) for r in reports),
                                "pairs_last": reports[-1]["pairs"] if reports else 0}
    if NOVEL_ARM in arms:
        out["admission"] = admission_summary(arms[NOVEL_ARM], arms["merge"])
        out["novel_minus_merge_later_points"] = {key: (
            None if out[NOVEL_ARM]["later"][key] is None or out["merge"]["later"][key] is None
            else round(100 * (out[NOVEL_ARM]["later"][key] - out["merge"]["later"][key]), 2))
            for key in ("sprint_recall@1", "accepted_recall@1", "merge_precision")}
    out["ingest_differs_from_localize"] = sum(r["ingest_differs_from_localize"]
                                              for r in arms["merge"])
    return out


def admission_summary(novel: list[dict[str, Any]], everything: list[dict[str, Any]]
                      ) -> dict[str, Any]:
    """The admitted map's size against the keep-everything map's: vertices at the end (and in
    traversals' worth of frames), frames stored per drive over the last fifth of the drives,
    disk bytes, and the per-frame cost (retrieval + HMM) of the last drives over the drives
    around the tenth (or the first ones of a shorter run)."""
    frames = novel[0]["frames"]
    tail = novel[-max(1, len(novel) // 5):]
    early = novel[8:11] or novel[:3]
    return {
        "vertices": novel[-1]["map_vertices_after"],
        "vertices_all": everything[-1]["map_vertices_after"],
        "traversals_worth": round(novel[-1]["map_vertices_after"] / frames, 2),
        "stored_fraction_last_fifth": round(
            sum(r["frames_stored"] for r in tail) / (frames * len(tail)), 4),
        "disk_bytes": novel[-1]["disk_bytes"],
        "disk_bytes_all": everything[-1]["disk_bytes"],
        "reingest_stored_fraction": round(novel[-1]["reingest_stored"] / frames, 4),
        "reingest_earlier_stored_fraction": round(float(np.mean(
            list(novel[-1]["reingest_stored_earlier"].values()))) / frames, 4),
        "frame_ms_early": round(float(np.median([r["frame_ms"] for r in early])), 4),
        "frame_ms_last": round(float(np.median([r["frame_ms"] for r in tail])), 4),
    }


def print_rows(seed: int, arms: dict[str, list[dict[str, Any]]]) -> None:
    print(f"\nseed {seed}")
    print(f"{'trav':>4} {'cond':>5} {'match':>5} | {'merge R@1':>9} {'acc.':>6} {'prec':>6} "
          f"{'edges':>5} {'wrongM':>6} | {'no-merge R@1':>12} {'acc.':>6} {'prec':>6} | "
          f"{'kNN@1':>6} {'kNN@10':>6}")
    for a, b in zip(arms["merge"], arms["no-merge"], strict=True):
        def pct(v: float | None) -> str:
            return "   -  " if v is None else f"{100 * v:5.1f}%"
        print(f"{a['traversal']:>4} {a['condition']:>5} {a['frames_with_match']:>5} | "
              f"{pct(a['sprint_recall@1']):>9} {pct(a['accepted_recall@1']):>6} "
              f"{pct(a['precision']):>6} {a['edges_added']:>5} {a['merged_wrong']:>6} | "
              f"{pct(b['sprint_recall@1']):>12} {pct(b['accepted_recall@1']):>6} "
              f"{pct(b['precision']):>6} | "
              f"{pct(a['knn_recall@1']):>6} {pct(a['knn_recall@10']):>6}", flush=True)


def print_summary(label: str, s: dict[str, Any]) -> None:
    def pct(v: float | None) -> str:
        return "-" if v is None else f"{100 * v:.1f} %"
    print(f"\n{label}: SPRINT recall@1 (precision of accepted decisions) "
          "{causal recall@1} [k-NN@1 / k-NN@10]")
    for arm in ARMS:
        e, lat = s[arm]["earlier"], s[arm]["later"]
        print(f"  {arm:>8}: earlier half {pct(e['sprint_recall@1'])} ({pct(e['precision'])}) "
              f"{{{pct(e['online_sprint_recall@1'])}}} "
              f"[{pct(e['knn_recall@1'])} / {pct(e['knn_recall@10'])}], "
              f"later half {pct(lat['sprint_recall@1'])} ({pct(lat['precision'])}) "
              f"{{{pct(lat['online_sprint_recall@1'])}}} "
              f"[{pct(lat['knn_recall@1'])} / {pct(lat['knn_recall@10'])}], "
              f"later - earlier {s[arm]['later_minus_earlier_points']:+.1f} points")
    for arm in ARMS:
        e, lat = s[arm]["earlier"], s[arm]["later"]
        print(f"  {arm:>8}: recall@1 of accepted decisions: earlier half "
              f"{pct(e['accepted_recall@1'])} {{{pct(e['online_accepted_recall@1'])}}}, later half "
              f"{pct(lat['accepted_recall@1'])} {{{pct(lat['online_accepted_recall@1'])}}}, "
              f"later - earlier {s[arm]['accepted_later_minus_earlier_points']:+.1f} points")
    for arm in ARMS:
        snap = s[arm].get("snapshot")
        if snap:
            print(f"  {arm:>8}: later half on the frames the map before it can match "
                  f"({snap['frames']:.0f}): against that map {pct(snap['snapshot_recall@1'])}, "
                  f"against the grown map {pct(snap['grown_recall@1'])}, grown - before "
                  f"{snap['grown_minus_snapshot_points']:+.1f} points (the map's growth alone)")
    merge = s["merge"]
    print(f"  merged decisions (edges): precision {pct(merge['earlier']['merge_precision'])} "
          f"({merge['earlier']['merged_wrong']:.0f} wrong of {merge['earlier']['merged']:.0f}) on the "
          f"earlier half, {pct(merge['later']['merge_precision'])} "
          f"({merge['later']['merged_wrong']:.0f} wrong of {merge['later']['merged']:.0f}) on the later")
    print(f"  merge - no-merge on the later half: "
          f"{s['merge_minus_no_merge_later_points']:+.1f} points "
          f"(causal, streaming decisions: {s['online_merge_minus_no_merge_later_points']:+.1f}); "
          f"accepted decisions {s['accepted_merge_minus_no_merge_later_points']:+.1f} "
          f"(causal {s['online_accepted_merge_minus_no_merge_later_points']:+.1f})")
    if "learn_minus_merge_later_points" in s:
        learn = s["merge+learn"]
        print(f"  merge+learn: later half {pct(learn['later']['sprint_recall@1'])} "
              f"(merge precision {pct(learn['later']['merge_precision'])}); learn - merge on "
              f"the later half (points): {s['learn_minus_merge_later_points']}; projection "
              f"adopted {s['learn_adopted']['adopted']} of {s['learn_adopted']['tried']} times "
              f"(last from {s['learn_adopted']['pairs_last']} pairs)")
    if "admission" in s:
        a, d = s["admission"], s["novel_minus_merge_later_points"]
        print(f"  merge+novel (admission): {a['vertices']:.0f} vertices "
              f"({a['traversals_worth']:.1f} traversals' worth; keep-everything "
              f"{a['vertices_all']:.0f}), {100 * a['stored_fraction_last_fifth']:.1f} % of a "
              f"drive stored per drive over the last fifth, disk {a['disk_bytes'] / 1e6:.1f} "
              f"MB (keep-everything {a['disk_bytes_all'] / 1e6:.1f} MB), per-frame cost "
              f"{a['frame_ms_early']:.2f} -> {a['frame_ms_last']:.2f} ms; the last drive "
              f"again stores {100 * a['reingest_stored_fraction']:.1f} %, the drives at a "
              f"quarter, half and three quarters "
              f"{100 * a['reingest_earlier_stored_fraction']:.1f} %; novel - merge on "
              f"the later half (points): {d}")
    if s.get("ingest_differs_from_localize"):
        print(f"  WARNING: on {s['ingest_differs_from_localize']:.0f} frames ingest's decision "
              "differs from localize(smooth=True)'s: the runs score different procedures")


def mean_summary(summaries: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean over seeds of the headline numbers."""
    def mean(path: tuple[str, ...]) -> float | None:
        values = []
        for s in summaries:
            v: Any = s
            for key in path:
                v = v[key]
            if v is not None:
                values.append(float(v))
        return round(float(np.mean(values)), 4) if values else None

    out: dict[str, Any] = {}
    learned = ("merge+learn",) if "merge+learn" in summaries[0] else ()
    novel = (NOVEL_ARM,) if NOVEL_ARM in summaries[0] else ()
    for arm in ARMS + learned + novel:
        out[arm] = {
            half: {key: mean((arm, half, key)) for key in
                   ("sprint_recall@1", "online_sprint_recall@1", "accepted_recall@1",
                    "online_accepted_recall@1", "precision", "merge_precision",
                    "merged", "merged_wrong", "knn_recall@1", "knn_recall@10")}
            for half in ("earlier", "later")
        }
        for key in ("later_minus_earlier_points", "accepted_later_minus_earlier_points"):
            out[arm][key] = mean((arm, key))
        if all(s[arm].get("snapshot") for s in summaries):
            out[arm]["snapshot"] = {key: mean((arm, "snapshot", key)) for key in (
                "frames", "snapshot_recall@1", "grown_recall@1", "grown_minus_snapshot_points")}
    for key in ("merge_minus_no_merge_later_points", "online_merge_minus_no_merge_later_points",
                "accepted_merge_minus_no_merge_later_points",
                "online_accepted_merge_minus_no_merge_later_points",
                "ingest_differs_from_localize"):
        out[key] = mean((key,))
    if novel:
        out["admission"] = {key: mean(("admission", key)) for key in summaries[0]["admission"]}
        out["novel_minus_merge_later_points"] = {
            key: mean(("novel_minus_merge_later_points", key))
            for key in summaries[0]["novel_minus_merge_later_points"]}
    if learned:
        out["learn_minus_merge_later_points"] = {key: mean(("learn_minus_merge_later_points", key))
                                                 for key in summaries[0][
                                                     "learn_minus_merge_later_points"]}
        out["learn_adopted"] = {key: sum(s["learn_adopted"][key] for s in summaries)
                                for key in ("tried", "adopted")}
        out["learn_adopted"]["pairs_last"] = summaries[-1]["learn_adopted"]["pairs_last"]
    return out


def plot(path: Path, results: list[dict[str, Any]]) -> None:
    """Recall@1 per traversal (mean over seeds) per arm; with ``--admission`` also the map's
    vertices and the per-frame cost against drives, admission on and off."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    admitted = NOVEL_ARM in results[0]["arms"]
    fig, axes = plt.subplots(1, 3 if admitted else 1, figsize=(15 if admitted else 8, 4.2),
                             squeeze=False)
    ax = axes[0][0]

    def mean_of(arm: str, key: str) -> Any:
        return np.mean([[r[key] for r in res["arms"][arm]] for res in results], axis=0)

    x = [r["traversal"] for r in results[0]["arms"]["merge"]]
    styles = (("merge", "o-"), ("no-merge", "s--")) + (((NOVEL_ARM, "^-"),) if admitted else ())
    for arm, style in styles:
        ax.plot(x, 100 * mean_of(arm, "sprint_recall@1"), style, ms=3,
                label=f"SPRINT, {arm}" + (f" (mean of {len(results)} seeds)"
                                          if len(results) > 1 else ""))
    ax.plot(x, 100 * mean_of("merge", "knn_recall@1"), ":", color="grey",
            label="exact k-NN@1")
    ax.axvline((len(x) + 1) // 2 - 0.5, color="lightgrey", lw=0.8)  # earlier | later half
    ax.set(xlabel="traversal (localised against all earlier ones)", ylabel="recall@1 (%)",
           title="Lifelong: recall@1 per traversal", ylim=(0, 100))
    ax.legend(loc="lower right")
    if admitted:
        for arm, style in (("merge", "o-"), (NOVEL_ARM, "^-")):
            axes[0][1].plot(x, mean_of(arm, "map_vertices_after"), style, ms=3,
                            label="keep everything" if arm == "merge" else "admission novel")
            axes[0][2].plot(x, mean_of(arm, "frame_ms"), style, ms=3, label=arm)
        axes[0][1].set(xlabel="traversal", ylabel="map vertices", title="Map size")
        axes[0][2].set(xlabel="traversal", ylabel="ms per frame (retrieval + HMM)",
                       title="Per-frame cost", ylim=(0, None))
        axes[0][1].legend(loc="upper left")
        axes[0][2].legend(loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--traversals", type=int, default=24)
    parser.add_argument("--frames", type=int, default=300, help="frames per traversal")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2],
                        help="one city per seed; each is reported, then the mean")
    parser.add_argument("--world", choices=[*sorted(WORLDS), "latent"], default="easy",
                        help="easy: the 3 x 3 city; hard: 4 x 4, one facade style, harsh "
                             "conditions; latent: the descriptor-level world family")
    parser.add_argument("--quick", action="store_true",
                        help="8 traversals x 60 frames, one seed (a smoke run)")
    parser.add_argument("--workers", type=int, default=None, help="rendering threads")
    parser.add_argument("--no-thumbnails", action="store_true",
                        help="keep no thumbnails: the merge verifies nothing on the images")
    parser.add_argument("--learn-every", type=int, default=0, metavar="N",
                        help="add an arm 'merge+learn': the map learns its descriptor from its "
                        "merges (index --learn) after every N drives")
    parser.add_argument("--admission", action="store_true",
                        help="add an arm 'merge+novel': the merge run on a map that stores "
                        "only what it lacks (init --admission novel)")
    parser.add_argument("--json", type=Path, help="write per-traversal rows and summaries here")
    parser.add_argument("--png", type=Path, help="plot recall@1 per traversal here")
    args = parser.parse_args(argv)
    if args.quick:
        args.traversals, args.frames, args.seeds = 8, 60, args.seeds[:1]
    if args.traversals < 4 or args.frames < 10:
        parser.error("need --traversals >= 4 and --frames >= 10")
    city: CityConfig | LatentConfig = WORLDS.get(args.world, LATENT)
    map_config = (MapConfig(dim=LATENT.dim) if args.world == "latent"
                  else MapConfig.for_descriptor("hog"))
    started = time.perf_counter()
    results = []
    for seed in args.seeds:
        if isinstance(city, LatentConfig):
            drives, gt, render_s = latent_drives(seed, args.traversals, args.frames, city)
        else:
            drives, gt, render_s = render_drives(seed, args.traversals, args.frames, city,
                                                 args.workers, not args.no_thumbnails)
        print(f"seed {seed}: rendered and described {len(drives)} x {args.frames} frames in "
              f"{render_s:.1f} s", flush=True)
        arms = {}
        with tempfile.TemporaryDirectory() as tmp:
            for arm in ARMS:
                arms[arm] = run_arm(drives, gt, arm == "merge", Path(tmp), map_config)
            if args.admission:
                arms[NOVEL_ARM] = run_arm(drives, gt, True, Path(tmp), map_config.replace(
                    admission={"mode": "novel"}))
            if args.learn_every:
                arms["merge+learn"] = run_arm(drives, gt, True, Path(tmp), map_config,
                                              args.learn_every)
        print_rows(seed, arms)
        summary = summarise(arms)
        print_summary(f"seed {seed}", summary)
        results.append({"seed": seed, "render_seconds": round(render_s, 1), "arms": arms,
                        "summary": summary})
    mean = mean_summary([r["summary"] for r in results])
    if len(results) > 1:
        print_summary(f"mean of {len(results)} seeds", mean)
    seconds = time.perf_counter() - started
    print(f"\n{seconds:.0f} s in all")
    out = {
        "args": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "city": city.to_dict(),
        "ground_truth": city.ground_truth_spec().to_dict(),
        "world": args.world,
        "map_config": map_config.to_dict(),
        "seeds": results,
        "mean": mean,
        "seconds": round(seconds, 1),
    }
    if args.json:
        args.json.write_text(json.dumps(out, indent=2) + "\n")
    if args.png:
        plot(args.png, results)
    return 0


if __name__ == "__main__":
    sys.exit(main())
