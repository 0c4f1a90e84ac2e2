"""Ray benchmarks (issue 16 item 4): the ingest farm against serial ingest, the fanned-out search
against the in-process one, and the per-segment figures the sizing in ``docs/fleet.md`` rests on.

Three sections, each printing a table; ``--json OUT`` writes them all. Ratios are measured in one
run, back to back, on the same machine (it may be shared: compare the ratios, not the absolutes).

* ``ingest``: ``--drives`` drives of ``--frames`` precomputed descriptors (``.npy``) over a base
  map of ``--base`` vertices; serial ``SprintMap.ingest_drives`` against ``farm_ingest`` on a
  local Ray runtime (``--ray-cpus``); frames/s of each, their ratio, the drives the farm had to
  localise again, and whether both maps hold the same sequences and edges.
* ``search``: a flat map of ``--vertices`` vertices cut into ``--shards`` retrieval shards on a
  simulated cluster of as many nodes (``ray.cluster_utils.Cluster``); per search of 1, 16 and
  64 queries: the in-process exact search, the fanned-out one (equal answers checked), and the
  overhead (their difference), per search and per query.
* ``segments``: the segmented IVF-PQ index of maps of ``--segment-sizes`` vertices (trained on
  the map, the map's defaults: 1,024 lists, 16 probed, PQ16 after PCA to 128, 100 re-ranked):
  search latency per query, and disk bytes per vertex (shards, index, LMDB).

::

    python tools/bench_ray.py --json ray.json
    python tools/bench_ray.py --only search --vertices 1000000
    python tools/bench_ray.py --quick          # small sizes, a smoke run
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map.config import MapConfig
from sprint_map.drives import Drive
from sprint_map.map import SprintMap

DIM = 128
AREA = 1000  # places per area: one drive's worth


def unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def areas(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    """``n`` areas of ``AREA`` places; neighbouring places alike (a moving average of 4)."""
    out = []
    for _ in range(n):
        raw = rng.standard_normal((AREA + 3, DIM))
        out.append(unit(np.cumsum(raw, axis=0)[3:] - np.cumsum(raw, axis=0)[:-3]))
    return out


def traverse(places: np.ndarray, rng: np.random.Generator, noise: float) -> np.ndarray:
    """A drive over ``places``: noise of norm ~``noise`` per frame (places are unit-norm)."""
    return unit(places + noise * rng.standard_normal(places.shape) / np.sqrt(DIM))


def timed(fn: Any, repeat: int) -> list[float]:
    out = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        out.append((time.perf_counter() - start) * 1e3)
    return out


def map_state(path: Path) -> tuple[Any, ...]:
    with SprintMap.open(path, readonly=True) as m:
        seqs = tuple((s.seq_id, s.name, s.length) for s in m.sequences())
        edges = tuple((e.src_seq, e.src_image, e.dst_seq, e.dst_image, e.prob)
                      for e in m.edges())
    return seqs, edges


# --- ingest ---------------------------------------------------------------------------------
def bench_ingest(work: Path, base_vertices: int, drives: int, cpus: int, seed: int,
                 noise: float) -> dict[str, Any]:
    from sprint_map.fleet.farm import farm_ingest
    from sprint_map.fleet.runtime import connect

    rng = np.random.default_rng(seed)
    n_areas = max(drives, base_vertices // AREA)
    world = areas(rng, n_areas)
    base = work / "base.map"
    with SprintMap.create(base, MapConfig(dim=DIM, index_type="flat")) as m:
        for a in range(n_areas):
            m.add_sequence(traverse(world[a], rng, noise), name=f"base{a}")
    # each drive revisits its own area, but the last two revisit the first two drives' areas
    # (the farm localised them before those drives were committed: stale, localised again)
    order = [a % max(drives - 2, 1) for a in range(drives)]
    sources = []
    for n, a in enumerate(order):
        p = work / f"drive{n:03d}.npy"
        np.save(p, traverse(world[a], rng, noise))
        sources.append(str(p))
    frames = drives * AREA

    serial = work / "serial.map"
    shutil.copytree(base, serial)
    start = time.perf_counter()
    with SprintMap.open(serial) as m:
        m.ingest_drives([Drive(np.load(s), Path(s).stem, source=s) for s in sources])
    serial_s = time.perf_counter() - start

    t0 = time.perf_counter()
    connect("local", num_cpus=cpus)
    ray_start_s = time.perf_counter() - t0
    farmed = work / "farm.map"
    shutil.copytree(base, farmed)
    start = time.perf_counter()
    with SprintMap.open(farmed) as m:
        results = farm_ingest(m, sources)
    farm_s = time.perf_counter() - start
    relocalised = sum(r.relocalised is not None for r in results)
    return {"noise": noise, "base_vertices": n_areas * AREA, "drives": drives, "frames": frames,
            "ray_cpus": cpus, "ray_start_s": round(ray_start_s, 2),
            "serial_s": round(serial_s, 3), "farm_s": round(farm_s, 3),
            "serial_frames_per_s": round(frames / serial_s),
            "farm_frames_per_s": round(frames / farm_s),
            "farm_over_serial": round(serial_s / farm_s, 2),
            "relocalised": relocalised, "equal": map_state(serial) == map_state(farmed)}


# --- search ---------------------------------------------------------------------------------
def bench_search(work: Path, vertices: int, shards: int, repeat: int, seed: int
                 ) -> dict[str, Any]:
    import ray
    from ray.cluster_utils import Cluster

    from sprint_map.fleet.shards import ShardedIndex

    rng = np.random.default_rng(seed)
    path = work / "search.map"
    with SprintMap.create(path, MapConfig(dim=DIM, index_type="flat")) as m:
        for start in range(0, vertices, 100_000):
            m.add_sequence(unit(rng.standard_normal((min(100_000, vertices - start), DIM))))
    t0 = time.perf_counter()
    cluster = Cluster(initialize_head=True,
                      head_node_args={"num_cpus": 1, "include_dashboard": False})
    for _ in range(shards - 1):
        cluster.add_node(num_cpus=1)
    ray.init(address=cluster.address, log_to_driver=False, logging_level="ERROR")
    cluster.wait_for_nodes()
    cluster_s = time.perf_counter() - t0
    rows = []
    try:
        with SprintMap.open(path, readonly=True) as m:
            t0 = time.perf_counter()
            sharded = ShardedIndex(m, shards)
            shards_s = time.perf_counter() - t0
            m.search(unit(rng.standard_normal((1, DIM))), 10)  # load the index
            for batch in (1, 16, 64):
                q = unit(rng.standard_normal((batch, DIM)))
                equal = all(np.array_equal(a, b) for a, b in
                            zip(m.search(q, 10), sharded.search_live(q, 10), strict=True))
                local = timed(lambda q=q: m.search(q, 10), repeat)
                fanned = timed(lambda q=q: sharded.search_live(q, 10), repeat)
                noop = timed(lambda: ray.get([a.covered.remote() for a in sharded.actors]),
                             repeat)
                med_l, med_f = statistics.median(local), statistics.median(fanned)
                rows.append({"queries": batch, "in_process_ms": round(med_l, 3),
                             "fanned_out_ms": round(med_f, 3),
                             "fanned_out_p99_ms": round(float(np.percentile(fanned, 99)), 3),
                             "overhead_ms": round(med_f - med_l, 3),
                             "overhead_per_query_ms": round((med_f - med_l) / batch, 4),
                             "empty_round_trip_ms": round(statistics.median(noop), 3),
                             "equal": equal})
            sharded.close()
    finally:
        ray.shutdown()
        cluster.shutdown()
    return {"vertices": vertices, "shards": shards, "nodes": shards,
            "cluster_start_s": round(cluster_s, 2), "shards_start_s": round(shards_s, 2),
            "rows": rows}


# --- segments -------------------------------------------------------------------------------
def dir_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def bench_segments(work: Path, sizes: list[int], repeat: int, seed: int) -> list[dict[str, Any]]:
    rng = np.random.default_rng(seed)
    centres = unit(rng.standard_normal((20_000, DIM)))
    out = []
    for size in sizes:
        path = work / f"seg{size}.map"
        with SprintMap.create(path, MapConfig(dim=DIM, index_type="ivf-pq")) as m:
            for start in range(0, size, 100_000):
                n = min(100_000, size - start)
                m.add_sequence(unit(centres[rng.integers(0, len(centres), n)]
                                    + 0.5 * rng.standard_normal((n, DIM)) / np.sqrt(DIM)))
            t0 = time.perf_counter()
            m.rebuild_index(train=True)  # trained on this map's sample, every row encoded
            train_s = time.perf_counter() - t0
        with SprintMap.open(path, readonly=True) as m:
            m.search(unit(rng.standard_normal((1, DIM))), 10)  # open the segments
            queries = unit(centres[rng.integers(0, len(centres), repeat)]
                           + 0.5 * rng.standard_normal((repeat, DIM)) / np.sqrt(DIM))
            ms = [timed(lambda q=q: m.search(q[None], 10), 1)[0] for q in queries]
            index = m.info()["index"]
        total = dir_bytes(path)
        index_bytes = dir_bytes(path / "index") if (path / "index").exists() else 0
        shard_bytes = dir_bytes(path / "shards") if (path / "shards").exists() else 0
        out.append({"vertices": size, "index": index.get("type", ""),
                    "segments": index.get("segments"), "train_s": round(train_s, 1),
                    "search_p50_ms": round(float(np.percentile(ms, 50)), 3),
                    "search_p99_ms": round(float(np.percentile(ms, 99)), 3),
                    "bytes_per_vertex": round(total / size, 1),
                    "index_bytes_per_vertex": round(index_bytes / size, 1),
                    "shard_bytes_per_vertex": round(shard_bytes / size, 1)})
        shutil.rmtree(path)
    return out


def table(title: str, rows: list[dict[str, Any]]) -> None:
    print(f"\n{title}")
    if not rows:
        return
    keys = list(rows[0])
    print(" | ".join(keys))
    for row in rows:
        print(" | ".join(str(row[k]) for k in keys))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--only", choices=["ingest", "search", "segments"], action="append")
    parser.add_argument("--base", type=int, default=100_000, help="base map vertices (ingest)")
    parser.add_argument("--drives", type=int, default=10)
    parser.add_argument("--ray-cpus", type=int, default=2)
    parser.add_argument("--noise", type=float, nargs="+", default=[0.5, 1.4],
                        help="drive noise (norm per frame, places unit-norm): 0.5 keeps a "
                        "frame's k nearest in its own area, 1.4 puts most at the noise floor, "
                        "in any area")
    parser.add_argument("--vertices", type=int, default=300_000, help="search map vertices")
    parser.add_argument("--shards", type=int, default=3)
    parser.add_argument("--segment-sizes", type=int, nargs="+", default=[250_000, 1_000_000])
    parser.add_argument("--repeat", type=int, default=200)
    parser.add_argument("--seed", type=int, default=16)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--workdir", type=Path)
    args = parser.parse_args(argv)
    if args.quick:
        args.base, args.drives, args.vertices = 5_000, 4, 20_000
        args.segment_sizes, args.repeat = [20_000], 20
    only = args.only or ["ingest", "search", "segments"]
    work = Path(tempfile.mkdtemp(prefix="bench-ray-", dir=args.workdir))
    out: dict[str, Any] = {}
    try:
        if "ingest" in only:
            out["ingest"] = []
            for noise in args.noise:
                sub = work / f"ingest-{noise}"
                sub.mkdir()
                out["ingest"].append(bench_ingest(sub, args.base, args.drives, args.ray_cpus,
                                                  args.seed, noise))
            import ray

            ray.shutdown()
            table("Ray ingest farm vs serial ingest", out["ingest"])
        if "search" in only:
            (work / "search").mkdir()
            out["search"] = bench_search(work / "search", args.vertices, args.shards,
                                         args.repeat, args.seed)
            print(f"\n{out['search']['vertices']:,} vertices in {out['search']['shards']} shards "
                  f"on {out['search']['nodes']} nodes")
            table("Fanned-out search vs in process (ms per search)", out["search"]["rows"])
        if "segments" in only:
            (work / "segments").mkdir()
            out["segments"] = bench_segments(work / "segments", args.segment_sizes,
                                             args.repeat, args.seed)
            table("Segmented IVF-PQ index per node", out["segments"])
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
