"""Joining maps (issue 54): cost of the copy and of the localisation, and quality.

Two vans map apart; their maps are joined (``SprintMap.join``). Two kinds of figures:

**Quality** (``--world latent`` or ``--world nordland``), judged by the snapshot comparison: the
same held-back frames answered by several maps, each decision scored by the ground truth of the
vertex it names (positions within the world's radius and heading):

- ``A`` alone, ``B`` alone: each van's map (its drives ingested in time order);
- ``joined``: a copy of ``A`` joined with ``B`` (``B``'s drives localised against ``A``);
- ``serial``: one map that ingested every drive of both vans in time order.

Recall@1 of the causal answers (what a vehicle gets) over the held-back frames that have a true
match in the map answering; the joined map is also scored on each van's own area (the frames
``A``, resp. ``B``, can match) against that van's map alone. Merge precision: the cross-map edges
the join added (``B``'s drives to ``A``'s) and, for the same drives, the edges ``serial``'s ingest
added from ``B``'s drives to ``A``'s; an edge is right if its two ends are within the radius.
Localisation cost: the join's ms/frame against ingesting ``B``'s drives into a copy of ``A`` (the
same drives, the same run).

- ``latent``: the descriptor-level world (:mod:`sprint_map.synth.latent`, preset
  ``latent-lifelong``); traversals alternate between the vans, the last ``--held`` are held back.
- ``city``: the rendered city (:mod:`sprint_map.synth.city`, HoG, thumbnails), the same split.
- ``nordland``: a cut of the real ride (HoG, ``/work/shared/data/nordland``): van A drove summer
  frames [a0, a1), van B winter frames [b0, b1) (overlapping, so the maps can merge); held back:
  winter frames over A's area and summer frames over B's, i.e. frames neither map holds.
  Position = frame index; a match is within one frame.

**Copy** (``--copy V``): a source of ``V`` random vertices (drives of ``--drive-frames``) joined
with ``--no-merge`` into a target of ``V`` vertices, in a child process: vertices/s and the
child's peak RSS (``--index-type``: the maps' index; the exact ``flat`` one holds every row in
memory, so a join's RSS then grows with the maps).

    python tools/bench_join.py --world latent --json join-latent.json
    python tools/bench_join.py --world city --json join-city.json
    python tools/bench_join.py --world nordland --json join-nordland.json
    python tools/bench_join.py --copy 200000 --dim 128
"""

from __future__ import annotations

import argparse
import json
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map import MapConfig, SprintMap
from sprint_map.config import StoreOptions

NORDLAND = Path("/work/shared/data/nordland")


@dataclass
class Drive:
    name: str
    rows: np.ndarray
    xy: np.ndarray  # (n, 2)
    heading: np.ndarray  # (n,) degrees, NaN: none
    thumbnails: list[bytes] | None = None


@dataclass
class World:
    config: MapConfig
    van_a: list[Drive]
    van_b: list[Drive]
    order: list[Drive]  # both vans' drives in time order
    held: list[Drive]
    radius: float
    heading_deg: float


def latent_world(seed: int, traversals: int, frames: int, held: int) -> World:
    from sprint_map.synth.latent import LATENT_PRESETS, make_latent

    config = LATENT_PRESETS["latent-lifelong"]
    world = make_latent(traversals, frames, seed, config)
    drives = [Drive(t.name, t.descriptors.astype(np.float32), t.positions[:, 1:3],
                    t.positions[:, 3]) for t in world.traversals]
    mapped, kept = drives[:-held], drives[-held:]
    return World(MapConfig(dim=drives[0].rows.shape[1]), mapped[0::2], mapped[1::2], mapped,
                 kept, config.radius_m, config.heading_deg)


def city_world(seed: int, traversals: int, frames: int, held: int) -> World:
    """The rendered city (HoG of its images, with a thumbnail of each frame: the merge
    verifies on them, as ``ingest --thumbnails`` does)."""
    from sprint_map.frontend.thumbnails import make_thumbnail
    from sprint_map.synth import CityConfig, iter_city

    config = CityConfig()
    spec = MapConfig.for_descriptor("hog").descriptor_spec()
    assert spec is not None
    drives = []
    for t in iter_city(traversals, frames, seed=seed, config=config):
        drives.append(Drive(t.name, spec.describe_batch(t.images).astype(np.float32),
                            t.positions[:, 1:3].copy(), t.positions[:, 3].copy(),
                            [make_thumbnail(image) for image in t.images]))
    mapped, kept = drives[:-held], drives[-held:]
    gt = config.ground_truth_spec()
    return World(MapConfig.for_descriptor("hog"), mapped[0::2], mapped[1::2], mapped, kept,
                 gt.radius_m, 180.0 if gt.heading_deg is None else gt.heading_deg)


def nordland_world(a: tuple[int, int], b: tuple[int, int], chunk: int) -> World:
    import cv2

    from sprint_map.frontend.descriptors import DescriptorSpec

    spec = DescriptorSpec("hog", {})

    def rows(season: str, lo: int, hi: int) -> np.ndarray:
        files = [NORDLAND / season / f"images-{10 * (i + 1):05d}.png" for i in range(lo, hi)]
        images = [cv2.imread(str(f)) for f in files]
        assert all(i is not None for i in images), f"unreadable frames of {season}"
        return spec.describe_batch(i for i in images if i is not None).astype(np.float32)

    def drives(season: str, lo: int, hi: int) -> list[Drive]:
        out = []
        for start in range(lo, hi, chunk):
            stop = min(start + chunk, hi)
            idx = np.arange(start, stop, dtype=float)
            out.append(Drive(f"{season}-{start}", rows(season, start, stop),
                             np.c_[idx, np.zeros(len(idx))], np.full(len(idx), np.nan)))
        return out

    van_a, van_b = drives("summer", *a), drives("winter", *b)
    held = drives("winter", a[0], b[0]) + drives("summer", a[1], b[1])
    return World(MapConfig.for_descriptor("hog"), van_a, van_b, van_a + van_b, held, 1.0, 180.0)


def ingest(m: SprintMap, d: Drive) -> Any:
    """As ``sprint-map ingest --positions`` does: the positions stored, and used as fixes."""
    return m.ingest(d.rows, name=d.name, positions=np.c_[d.xy, d.heading],
                    fixes=np.c_[d.xy, np.full(len(d.xy), np.nan)], thumbnails=d.thumbnails)


def build(path: Path, config: MapConfig, drives: list[Drive]) -> list[Any]:
    with SprintMap.create(path, config) as m:
        return [ingest(m, d) for d in drives]


class Places:
    """The positions of every vertex of a map, for scoring its answers."""

    def __init__(self, m: SprintMap) -> None:
        from scipy.spatial import cKDTree

        self.by_seq: dict[int, np.ndarray] = {}
        for s in m.sequences():
            pos = m.positions(s.seq_id)
            assert pos is not None
            self.by_seq[s.seq_id] = pos[:, [0, 1, 2]]
        self.all = np.concatenate(list(self.by_seq.values()))
        self.tree = cKDTree(self.all[:, :2])

    def at(self, seq: int, image: int | None) -> np.ndarray:
        assert image is not None
        row: np.ndarray = self.by_seq[seq][image]
        return row


def same_place(p: np.ndarray, xy: np.ndarray, heading: float, radius: float,
               max_heading: float) -> bool:
    if np.hypot(*(p[:2] - xy)) > radius:
        return False
    if np.isnan(heading) or np.isnan(p[2]):
        return True
    return bool(abs((p[2] - heading + 180) % 360 - 180) <= max_heading)


def score(path: Path, world: World) -> dict[str, np.ndarray]:
    """Per held-back frame: whether the map has a true match, whether its causal answer is
    right."""
    matchable, correct = [], []
    with SprintMap.open(path, readonly=True) as m:
        places = Places(m)
        for d in world.held:
            decisions, _ = m.localize(d.rows)
            for dec, xy, hd in zip(decisions, d.xy, d.heading, strict=True):
                near = places.tree.query_ball_point(xy, world.radius)
                matchable.append(any(same_place(places.all[i], xy, hd, world.radius,
                                                world.heading_deg) for i in near))
                correct.append(dec.seq_id is not None and same_place(
                    places.at(dec.seq_id, dec.image_id), xy, hd, world.radius,
                    world.heading_deg))
    return {"matchable": np.array(matchable), "correct": np.array(correct)}


def recall(s: dict[str, np.ndarray], on: np.ndarray) -> float:
    return round(100.0 * float(s["correct"][on].mean()), 2) if on.any() else float("nan")


def merge_precision(path: Path, world: World, added_by: set[str], into: set[str]) -> dict[str, Any]:
    """Edges added by the drives ``added_by`` that join one of them to a drive of ``into``."""
    with SprintMap.open(path, readonly=True) as m:
        places = Places(m)
        names = {s.seq_id: s.name for s in m.sequences()}
        right = total = 0
        for e in m.edges():
            if e.added_by is None or names[e.added_by] not in added_by:
                continue
            if names[e.src_seq] not in into and names[e.dst_seq] not in into:
                continue
            total += 1
            a, b = places.at(e.src_seq, e.src_image), places.at(e.dst_seq, e.dst_image)
            right += int(same_place(a, b[:2], b[2], world.radius, world.heading_deg))
    return {"edges": total, "right": right,
            "precision": round(100.0 * right / total, 2) if total else None}


def quality(world: World, root: Path) -> dict[str, Any]:
    a, b, joined, serial, ingested = (root / n for n in ("a", "b", "joined", "serial",
                                                         "ingested"))
    build(a, world.config, world.van_a)
    build(b, world.config, world.van_b)
    build(serial, world.config, world.order)
    shutil.copytree(a, joined)
    shutil.copytree(a, ingested)
    with SprintMap.open(joined) as m:
        result = m.join(b)
    frames_b = sum(len(d.rows) for d in world.van_b)
    started = time.perf_counter()
    with SprintMap.open(ingested) as m:
        for d in world.van_b:
            ingest(m, d)
    ingest_s = time.perf_counter() - started
    scores = {name: score(root / name, world) for name in ("a", "b", "joined", "serial")}
    names_a, names_b = {d.name for d in world.van_a}, {d.name for d in world.van_b}
    report = result.to_dict()
    on_j = scores["joined"]["matchable"]
    out: dict[str, Any] = {
        "held_frames": int(len(on_j)),
        "recall_at_1": {
            "A_alone_on_A": recall(scores["a"], scores["a"]["matchable"]),
            "joined_on_A": recall(scores["joined"], scores["a"]["matchable"]),
            "B_alone_on_B": recall(scores["b"], scores["b"]["matchable"]),
            "joined_on_B": recall(scores["joined"], scores["b"]["matchable"]),
            "serial_on_A": recall(scores["serial"], scores["a"]["matchable"]),
            "serial_on_B": recall(scores["serial"], scores["b"]["matchable"]),
            "joined": recall(scores["joined"], on_j),
            "serial": recall(scores["serial"], on_j),
        },
        "merge_precision": {
            "join_cross_map": merge_precision(joined, world, names_b, names_a),
            "serial_ingest_same_drives": merge_precision(serial, world, names_b, names_a),
            "ingest_into_A_same_drives": merge_precision(ingested, world, names_b, names_a),
        },
        "localise_ms_per_frame": {
            "join": report["localise_ms_per_frame"],
            "ingest_into_A": round(1e3 * ingest_s / frames_b, 4),
        },
        "join": {k: report[k] for k in ("imported", "vertices_copied", "edges_copied",
                                        "cross_edges", "copy_seconds", "localise_seconds")},
        "connected": [d["connected"] for d in report["drives"]],
    }
    r = out["recall_at_1"]
    ms = out["localise_ms_per_frame"]
    out["targets"] = {
        "joined_no_worse_than_A_alone": bool(r["joined_on_A"] >= r["A_alone_on_A"]),
        "joined_no_worse_than_B_alone": bool(r["joined_on_B"] >= r["B_alone_on_B"]),
        "joined_within_1pt_of_serial": bool(r["joined"] >= r["serial"] - 1.0),
        "localisation_within_1.2x_of_ingest": bool(ms["join"] <= 1.2 * ms["ingest_into_A"]),
    }
    pj = out["merge_precision"]["join_cross_map"]["precision"]
    ps = out["merge_precision"]["serial_ingest_same_drives"]["precision"]
    out["targets"]["merge_precision_at_least_ingests"] = (
        None if pj is None or ps is None else bool(pj >= ps))
    return out


COPY_CHILD = """
import json, resource, sys, time
from sprint_map import SprintMap
target, source = sys.argv[1], sys.argv[2]
t = time.perf_counter()
with SprintMap.open(target) as m:
    r = m.join(source, merge=False).to_dict()
print(json.dumps({"seconds": time.perf_counter() - t, "copy_seconds": r["copy_seconds"],
                  "vertices": r["vertices_copied"],
                  "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def copy_bench(vertices: int, dim: int, drive_frames: int, root: Path, seed: int,
               index_type: str = "auto") -> dict[str, Any]:
    rng = np.random.default_rng(seed)
    config = MapConfig(dim=dim, store=StoreOptions(index_type=index_type))
    for name in ("target", "source"):
        with SprintMap.create(root / name, config) as m, m.service.group_commit():
            for i, start in enumerate(range(0, vertices, drive_frames)):
                n = min(drive_frames, vertices - start)
                rows = rng.standard_normal((n, dim)).astype(np.float32)
                xy = np.c_[np.arange(n, dtype=float), np.full(n, float(i))]
                m.add_sequence(rows, name=f"{name}-{i}", positions=xy)
    proc = subprocess.run([sys.executable, "-c", COPY_CHILD, str(root / "target"),
                           str(root / "source")], capture_output=True, text=True, check=True)
    child = json.loads(proc.stdout)
    with SprintMap.open(root / "target", readonly=True) as m:
        ok = m.check().ok
    return {"vertices": vertices, "dim": dim, "drive_frames": drive_frames,
            "index_type": index_type,
            "seconds": round(child["seconds"], 3), "copy_seconds": round(child["copy_seconds"], 3),
            "vertices_per_s": round(child["vertices"] / child["copy_seconds"]),
            "peak_rss_mb": round(child["rss_mb"], 1), "check_ok": ok,
            "targets": {"copy_100k_vertices_per_s":
                        bool(child["vertices"] / child["copy_seconds"] >= 100_000),
                        "rss_1.5GB": bool(child["rss_mb"] <= 1536)}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--world", choices=["latent", "city", "nordland"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--traversals", type=int, default=10)
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--held", type=int, default=2)
    ap.add_argument("--nordland-a", default="200,800", help="summer frames of van A: lo,hi")
    ap.add_argument("--nordland-b", default="600,1200", help="winter frames of van B: lo,hi")
    ap.add_argument("--chunk", type=int, default=200, help="nordland: frames per drive")
    ap.add_argument("--copy", type=int, default=0, metavar="V")
    ap.add_argument("--dim", type=int, default=128)
    ap.add_argument("--drive-frames", type=int, default=10_000)
    ap.add_argument("--index-type", default="auto", help="--copy: the maps' index_type")
    ap.add_argument("--json", dest="json_out")
    args = ap.parse_args()
    out: dict[str, Any] = {"command": " ".join(sys.argv)}
    with tempfile.TemporaryDirectory(prefix="bench-join-") as tmp:
        root = Path(tmp)
        if args.world == "latent":
            world = latent_world(args.seed, args.traversals, args.frames, args.held)
            out["latent"] = quality(world, root / "latent")
        elif args.world == "city":
            world = city_world(args.seed, args.traversals, args.frames, args.held)
            out["city"] = quality(world, root / "city")
        elif args.world == "nordland":
            a = tuple(int(x) for x in args.nordland_a.split(","))
            b = tuple(int(x) for x in args.nordland_b.split(","))
            world = nordland_world((a[0], a[1]), (b[0], b[1]), args.chunk)
            out["nordland"] = quality(world, root / "nordland")
        if args.copy:
            (root / "copy").mkdir()
            out["copy"] = copy_bench(args.copy, args.dim, args.drive_frames, root / "copy",
                                     args.seed, args.index_type)
    out["peak_rss_mb_parent"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    text = json.dumps(out, indent=2)
    print(text)
    if args.json_out:
        Path(args.json_out).write_text(text + "\n")


if __name__ == "__main__":
    main()
