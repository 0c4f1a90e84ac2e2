"""Ray benchmarks (issue 16 item 4): the ingest farm against serial ingest, the fanned-out search
against the in-process one, and the per-segment figures the sizing in ``docs/fleet.md`` rests on.

Four sections, each printing a table; ``--json OUT`` writes them all. Ratios are measured in one
run, back to back, on the same machine (it may be shared: compare the ratios, not the absolutes).

* ``ingest``: ``--drives`` drives of ``--frames`` precomputed descriptors (``.npy``) over a base
  map of ``--base`` vertices; serial ``SprintMap.ingest_drives`` against ``farm_ingest`` on a
  local Ray runtime (``--ray-cpus``); frames/s of each, their ratio, the drives the farm had to
  localise again, and whether both maps hold the same sequences and edges.
* ``search``: flat maps of ``--vertices`` vertices (default 20k and 300k) cut into ``--shards``
  retrieval shards on a simulated cluster of as many nodes (``ray.cluster_utils.Cluster``, one
  CPU each); per search of 1, 16 and 64 queries, p50 and p99: the in-process exact search, the
  fanned-out one over each path (equal answers checked), the overhead (fanned out - in
  process) and each path's empty round trip to the shards. Paths: ``socket`` (the shards' TCP
  channels, ``ShardedIndex``'s default), ``ray`` (one actor call per shard, the old path) and
  ``ray-dag`` (a Ray Compiled Graph over the same actors, for comparison; ``--no-dag`` skips
  it). In-process and fanned-out searches are timed interleaved, round by round; the
  in-process search runs one OpenMP thread, as each shard does; ``one_shard`` is the largest
  range searched in process alone (what each shard computes per search).
* ``segments``: the segmented IVF-PQ index of maps of ``--segment-sizes`` vertices (trained on
  the map, the map's defaults: lists following its size, 24 probed, PQ16, 100 re-ranked):
  search latency per query, and disk bytes per vertex (shards, index, LMDB).
* ``approx``: maps of ``--approx-sizes`` vertices searched by ``--shards`` approximate
  retrieval shards (``ShardedIndex(approximate=True)``: each its range of the map's index
  segments) on a simulated cluster, against the in-process search, one query per search;
  ``one_shard`` is the largest range searched in process (a shard's compute per query), and
  recall@10 of both against brute force.

::

    python tools/bench_ray.py --json ray.json
    python tools/bench_ray.py --only search --vertices 1000000
    python tools/bench_ray.py --quick          # small sizes, a smoke run
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map.config import MapConfig, StoreOptions
from sprint_map.map import SprintMap
from sprint_map.merge.drives import Drive

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
    with SprintMap.create(base, MapConfig(dim=DIM, store=StoreOptions(index_type="flat"))) as m:
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
def percentiles(ms: list[float]) -> tuple[float, float]:
    return round(float(np.percentile(ms, 50)), 3), round(float(np.percentile(ms, 99)), 3)


def interleaved(fns: dict[str, Any], repeat: int) -> dict[str, list[float]]:
    """``repeat`` rounds, each timing every function once in turn (ms): a machine whose load
    drifts during the run weighs on every path alike."""
    out: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeat):
        for name, fn in fns.items():
            out[name].append(timed(fn, 1)[0])
    return out


def compiled_dag(ray: Any, actors: list[Any], method: str, *args: Any) -> Any:
    """A Ray Compiled Graph calling ``method`` on every actor with the input (and ``args``)."""
    from ray.dag import InputNode, MultiOutputNode

    with InputNode() as inp:
        dag = MultiOutputNode([getattr(actor, method).bind(inp, *args) for actor in actors])
    return dag.experimental_compile()


def search_rows(vertices: int, batch: int, times: dict[str, list[float]], pings: dict[str, Any],
                equal: dict[str, bool]) -> list[dict[str, Any]]:
    local_p50, local_p99 = percentiles(times["in-process"])
    alone = percentiles(times["one-shard"])[0]
    rows = []
    for path, ms in times.items():
        if path in ("in-process", "one-shard"):
            continue
        p50, p99 = percentiles(ms)
        trip = percentiles(pings[path]) if path in pings else (float("nan"),) * 2
        rows.append({"vertices": vertices, "queries": batch, "path": path,
                     "in_process_p50_ms": local_p50, "in_process_p99_ms": local_p99,
                     "one_shard_p50_ms": alone, "fanned_out_p50_ms": p50, "fanned_out_p99_ms": p99,
                     "overhead_p50_ms": round(p50 - local_p50, 3),
                     "overhead_p99_ms": round(p99 - local_p99, 3),
                     "round_trip_p50_ms": trip[0], "round_trip_p99_ms": trip[1],
                     "equal": equal[path]})
    return rows


def bench_dag(ray: Any, m: SprintMap, actors: list[Any], alone: Any, vertices: int,
              repeat: int, rng: np.random.Generator) -> list[dict[str, Any]]:
    """The ``ray-dag`` rows: a Ray Compiled Graph of the shards' ``search`` against the
    in-process search, interleaved, and its empty round trip (the shards' no-op
    ``catch_up(0)``, a method that takes an input)."""
    from sprint_map.fleet.shards import merge_topk

    graph = compiled_dag(ray, actors, "search", 10)

    def dag_search(q: np.ndarray) -> Any:
        parts = ray.get(graph.execute(q))
        return merge_topk([p[0] for p in parts], [p[1] for p in parts], 10)

    rows: list[dict[str, Any]] = []
    try:
        for batch in (1, 16, 64):
            q = unit(rng.standard_normal((batch, DIM)))
            equal = {"ray-dag": all(np.array_equal(a, b) for a, b in
                                    zip(m.search(q, 10), dag_search(q), strict=True))}
            times = interleaved({"in-process": lambda q=q: m.search(q, 10),
                                 "one-shard": lambda q=q, w=alone: w.search(q, 10),
                                 "ray-dag": lambda q=q: dag_search(q)}, repeat)
            rows += search_rows(vertices, batch, times, {}, equal)
    finally:
        graph.teardown()
    ping_graph = compiled_dag(ray, actors, "catch_up")
    try:
        trip = percentiles(timed(lambda: ray.get(ping_graph.execute(0)), repeat))
    finally:
        ping_graph.teardown()
    for row in rows:
        row["round_trip_p50_ms"], row["round_trip_p99_ms"] = trip
    return rows


def simulated_cluster(nodes: int) -> Any:
    """A ``ray.cluster_utils.Cluster`` of ``nodes`` one-CPU nodes, joined by this driver."""
    import ray
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True,
                      head_node_args={"num_cpus": 1, "include_dashboard": False})
    for _ in range(nodes - 1):
        cluster.add_node(num_cpus=1)
    ray.init(address=cluster.address, log_to_driver=False, logging_level="ERROR")
    cluster.wait_for_nodes()
    return cluster


def bench_search(work: Path, sizes: list[int], shards: int, repeat: int, seed: int,
                 dag: bool = True) -> dict[str, Any]:
    """Per map size and batch (1, 16, 64 queries): the in-process exact search against the
    fanned-out one over each transport (``ray``: an actor call per shard, the old path;
    ``socket``: the shards' TCP channels, the default), timed interleaved, and each transport's
    empty round trip; then, on the same actors, a Ray Compiled Graph (``ray-dag``) against the
    in-process search again (its actors serve the graph in a loop: timed apart)."""
    import faiss
    import ray

    from sprint_map.fleet.shards import ShardedIndex, ShardWorker

    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    cluster = simulated_cluster(shards)
    cluster_s = time.perf_counter() - t0
    rows: list[dict[str, Any]] = []
    notes: dict[str, Any] = {}
    try:
        for vertices in sizes:
            path = work / f"search{vertices}.map"
            with SprintMap.create(path, MapConfig(dim=DIM, store=StoreOptions(index_type="flat"))) as m:
                for start in range(0, vertices, 100_000):
                    m.add_sequence(unit(rng.standard_normal((min(100_000, vertices - start),
                                                             DIM))))
            with SprintMap.open(path, readonly=True) as m:
                # one OpenMP thread, as each shard: two threads on two shared cores spin-wait
                # for each other (16 queries of 20k took 187 ms at load 5, against 2 alone)
                SprintMap.cap_search_threads(1)
                m.search(unit(rng.standard_normal((1, DIM))), 10)  # load the index
                notes["in_process_omp_threads"] = faiss.omp_get_max_threads()
                t0 = time.perf_counter()
                sharded = {t: ShardedIndex(m, shards, transport=t) for t in ("ray", "socket")}
                notes[f"shards_start_s_{vertices}"] = round(time.perf_counter() - t0, 2)
                assert sharded["socket"].transport == "socket"
                actors = sharded["socket"].actors
                # the largest range searched here, alone: what each shard computes per search
                a, b = max(sharded["socket"].ranges,
                           key=lambda r: (vertices if r[1] is None else r[1]) - r[0])
                alone = ShardWorker(None, a, b, DIM, np.ascontiguousarray(
                    m.vertex_rows(a, vertices if b is None else b)))
                for batch in (1, 16, 64):
                    q = unit(rng.standard_normal((batch, DIM)))
                    want = m.search(q, 10)
                    equal = {t: all(np.array_equal(a, b) for a, b in
                                    zip(want, s.search_live(q, 10), strict=True))
                             for t, s in sharded.items()}
                    fns = {"in-process": lambda q=q: m.search(q, 10),
                           "one-shard": lambda q=q, w=alone: w.search(q, 10),
                           **{t: lambda q=q, s=s: s.search_live(q, 10)
                              for t, s in sharded.items()}}
                    times = interleaved(fns, repeat)
                    pings = interleaved({t: s.ping for t, s in sharded.items()}, repeat)
                    rows += search_rows(vertices, batch, times, pings, equal)
                sharded["ray"].close()
                if dag:
                    try:
                        rows += bench_dag(ray, m, actors, alone, vertices, repeat, rng)
                    except Exception as exc:  # a beta API: record why, keep the rest
                        notes["ray_dag_error"] = f"{type(exc).__name__}: {exc}"
                sharded["socket"].close()
            shutil.rmtree(path)
    finally:
        ray.shutdown()
        cluster.shutdown()
    return {"sizes": sizes, "shards": shards, "nodes": shards, "repeat": repeat,
            "cluster_start_s": round(cluster_s, 2), **notes, "rows": rows}


# --- segments -------------------------------------------------------------------------------
def dir_bytes(path: Path) -> int:
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def bench_segments(work: Path, sizes: list[int], repeat: int, seed: int) -> list[dict[str, Any]]:
    rng = np.random.default_rng(seed)
    centres = unit(rng.standard_normal((20_000, DIM)))
    out = []
    for size in sizes:
        path = work / f"seg{size}.map"
        with SprintMap.create(path, MapConfig(dim=DIM, store=StoreOptions(index_type="ivf-pq"))) as m:
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


# --- approximate shards ---------------------------------------------------------------------
def knn_recall(got: np.ndarray, want: np.ndarray) -> float:
    """Mean |got's k ids intersect want's| / k."""
    return round(float(np.mean([len(set(a) & set(b)) for a, b in
                                zip(got.tolist(), want.tolist(), strict=True)])) / want.shape[1], 3)


def approx_times(m: SprintMap, sharded: Any, queries: np.ndarray,
                 largest: tuple[int, int | None]) -> dict[str, list[float]]:
    """Each query searched in process, in the largest range alone and through the shards,
    in turn (ms)."""
    out: dict[str, list[float]] = {"in-process": [], "one-shard": [], "sharded": []}
    for q in queries:
        one = q[None]
        for name, search in (("in-process", m.search), ("sharded", sharded.search),
                             ("one-shard", partial(m.search_within, start=largest[0],
                                                   stop=largest[1]))):
            t0 = time.perf_counter()
            search(one, 10)
            out[name].append(1000 * (time.perf_counter() - t0))
    return out


def bench_approx_shards(work: Path, sizes: list[int], shards: int, repeat: int, seed: int
                        ) -> list[dict[str, Any]]:
    """Per map size: the map's approximate index searched in process against ``shards``
    approximate retrieval shards (each its range of the map's segments) on a simulated
    cluster, one query per search, timed interleaved; ``one_shard``: the largest range searched
    in process alone (what each shard computes); recall@10 of each against brute force."""
    import faiss
    import ray

    from sprint_map.fleet.shards import ShardedIndex

    rng = np.random.default_rng(seed)
    centres = unit(rng.standard_normal((20_000, DIM)))
    cluster = simulated_cluster(shards)
    out = []
    try:
        for size in sizes:
            path = work / f"approx{size}.map"
            with SprintMap.create(path, MapConfig(dim=DIM, store=StoreOptions(
                    index_type="ivf-pq"))) as m:
                for start in range(0, size, 100_000):
                    n = min(100_000, size - start)
                    m.add_sequence(unit(centres[rng.integers(0, len(centres), n)]
                                        + 0.5 * rng.standard_normal((n, DIM)) / np.sqrt(DIM)))
                m.rebuild_index(train=True)  # trained on the whole map's sample
            with SprintMap.open(path, readonly=True) as m:
                SprintMap.cap_search_threads(1)
                queries = unit(centres[rng.integers(0, len(centres), repeat)]
                               + 0.5 * rng.standard_normal((repeat, DIM)) / np.sqrt(DIM))
                m.search(queries[:1], 10)  # open the segments
                sharded = ShardedIndex(m, shards, approximate=True)
                try:
                    a, b = max(sharded.ranges, key=lambda r: (size if r[1] is None else r[1])
                               - r[0])
                    m.search_within(queries[:1], 10, a, b)
                    times = approx_times(m, sharded, queries, (a, b))
                    want = faiss.knn(queries, m.vertex_rows(0), 10)[1]
                    recall = {"in_process": knn_recall(m.search(queries, 10)[1], want),
                              "sharded": knn_recall(sharded.search(queries, 10)[1], want)}
                    segments = len(m.index_segments())
                    ranges = sharded.ranges
                finally:
                    sharded.close()
            row: dict[str, Any] = {"vertices": size, "segments": segments, "shards": len(ranges),
                                   "largest_range": (size if b is None else b) - a}
            for name, ms in times.items():
                row[f"{name}_p50_ms"], row[f"{name}_p99_ms"] = percentiles(ms)
            row.update({f"recall@10_{k}": v for k, v in recall.items()})
            out.append(row)
            shutil.rmtree(path)
    finally:
        ray.shutdown()
        cluster.shutdown()
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
    parser.add_argument("--only", choices=["ingest", "search", "segments", "approx"],
                        action="append")
    parser.add_argument("--base", type=int, default=100_000, help="base map vertices (ingest)")
    parser.add_argument("--drives", type=int, default=10)
    parser.add_argument("--ray-cpus", type=int, default=2)
    parser.add_argument("--noise", type=float, nargs="+", default=[0.5, 1.4],
                        help="drive noise (norm per frame, places unit-norm): 0.5 keeps a "
                        "frame's k nearest in its own area, 1.4 puts most at the noise floor, "
                        "in any area")
    parser.add_argument("--vertices", type=int, nargs="+", default=[20_000, 300_000],
                        help="search maps' vertices")
    parser.add_argument("--no-dag", action="store_true",
                        help="skip the Ray Compiled Graph path of the search section")
    parser.add_argument("--shards", type=int, default=3)
    parser.add_argument("--segment-sizes", type=int, nargs="+", default=[250_000, 1_000_000])
    parser.add_argument("--approx-sizes", type=int, nargs="+", default=[1_000_000],
                        help="maps searched by approximate shards")
    parser.add_argument("--repeat", type=int, default=200)
    parser.add_argument("--seed", type=int, default=16)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--json", type=Path)
    parser.add_argument("--workdir", type=Path)
    args = parser.parse_args(argv)
    if args.quick:
        args.base, args.drives, args.vertices = 5_000, 4, [20_000]
        args.segment_sizes, args.approx_sizes, args.repeat = [20_000], [40_000], 20
    only = args.only or ["ingest", "search", "segments", "approx"]
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
                                         args.repeat, args.seed, dag=not args.no_dag)
            print(f"\n{out['search']['shards']} shards on {out['search']['nodes']} simulated "
                  f"nodes, {args.repeat} searches of each size")
            table("Fanned-out search vs in process (ms per search; overhead = fanned out - in "
                  "process)", out["search"]["rows"])
        if "segments" in only:
            (work / "segments").mkdir()
            out["segments"] = bench_segments(work / "segments", args.segment_sizes,
                                             args.repeat, args.seed)
            table("Segmented IVF-PQ index per node", out["segments"])
        if "approx" in only:
            (work / "approx").mkdir()
            out["approx"] = bench_approx_shards(work / "approx", args.approx_sizes,
                                                args.shards, args.repeat, args.seed)
            table("Approximate shards: each its range of the map's segments (ms per query)",
                  out["approx"])
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
