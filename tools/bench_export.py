"""Export benchmark: time, output size and peak memory of each export, against a baseline.

For each ``--vertices N`` a map is built once and cached (``--cache``, default
``/tmp/sprint-export-bench``; a map is reused only if its build finished): drives of
``--seq-len`` frames of random precomputed descriptors (as ``tools/bench_scale.py`` does; the
export never reads descriptors) along the streets of a synthetic city, every frame with an
``x, y, heading`` position, each drive committed with edges both ways to the earlier drive that
saw the same place (every ``--edge-every`` frames), so the map is one large component with
provenance on every edge.

Each export then runs in a *fresh process* (``sprint_map`` imported, map opened read-only):
GraphML at the vertex level (streamed) and at the sequence level, CSV, GeoJSON; and a
*baseline* process that opens the map and walks the same records (positions and edges, through
the same scan) without writing anything. Reported per run: wall seconds, output bytes, peak RSS
(``VmHWM``: heap plus the mapped LMDB pages it touched) and peak anonymous RSS (``RssAnon``
sampled every 20 ms: the heap alone), and the export's peak over the baseline's as a ratio. A
streamed export's peak does not grow with the map: compare its figures at 100k and 1M.

Up to ``--roundtrip-max`` vertices (default 100,000), the vertex-level GraphML is read back with
``networkx.read_graphml`` in another fresh process and compared with the vertex graph built in
memory from the map: nodes, edges and every attribute must be equal (``roundtrip: true``); the
reader's seconds and peak RSS are reported too.

    python tools/bench_export.py --vertices 100000 1000000 --json export.json
    python tools/bench_export.py --vertices 20000 --seq-len 200      # smoke run
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

MODES = ("baseline", "graphml-vertex", "graphml-sequence", "csv", "geojson")


def _status_kb(field: str) -> int:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    return 0


class AnonPeak:
    """Samples ``RssAnon`` every 20 ms in a thread; ``peak`` in MB."""

    def __init__(self) -> None:
        self.peak_kb = _status_kb("RssAnon")
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.02):
            self.peak_kb = max(self.peak_kb, _status_kb("RssAnon"))

    def stop(self) -> float:
        self._stop.set()
        self._thread.join()
        self.peak_kb = max(self.peak_kb, _status_kb("RssAnon"))
        return self.peak_kb / 1024


def build(path: Path, n_vertices: int, args: argparse.Namespace) -> dict[str, Any]:
    """Build the map streaming (one drive in memory at a time)."""
    from sprint_map.config import MapConfig, StoreOptions
    from sprint_map.map import SprintMap
    from sprint_map.storage.records import EdgeSpec

    rng = np.random.default_rng(args.seed)
    n_places = max(args.seq_len, n_vertices // args.revisits)
    n_streets = max(1, n_places // args.street_len)
    origin = rng.uniform(-5000, 5000, (n_streets, 2))
    angle = rng.uniform(0, 2 * np.pi, n_streets)
    last_seq = np.full(n_streets * args.street_len, -1, dtype=np.int64)
    last_img = np.zeros(n_streets * args.street_len, dtype=np.int64)
    config = MapConfig(dim=args.dim, store=StoreOptions(index_type="flat"))
    started = time.perf_counter()
    committed = 0
    with SprintMap.create(path, config) as m:
        while committed < n_vertices:
            frames = min(args.seq_len, n_vertices - committed)
            places = []
            while sum(len(p) for p in places) < frames:
                street = int(rng.integers(n_streets))
                start = int(rng.integers(0, args.street_len // 2))
                places.append(street * args.street_len + np.arange(start, args.street_len))
            place = np.concatenate(places)[:frames]
            street, along = place // args.street_len, place % args.street_len
            heading = angle[street]
            xy = origin[street] + (5.0 * along)[:, None] * np.stack(
                [np.cos(heading), np.sin(heading)], axis=1)
            positions = np.column_stack([xy + rng.normal(0, 1.0, xy.shape),
                                         np.degrees(heading) % 360])
            rows = rng.standard_normal((frames, args.dim), dtype=np.float32)
            edges = []
            for i in range(0, frames, args.edge_every):
                p = place[i]
                if last_seq[p] >= 0:
                    old = (int(last_seq[p]), int(last_img[p]))
                    prob = float(rng.uniform(0.5, 1.0))
                    edges.append(EdgeSpec((None, i), old, prob, i))
                    edges.append(EdgeSpec(old, (None, i), prob, i))
            added = m.add_sequence(rows, positions=positions, edges=edges)
            last_seq[place] = added.sequence.seq_id
            last_img[place] = np.arange(frames)
            committed += frames
        stats = m.stats()
    return {**stats, "build_s": round(time.perf_counter() - started, 1)}


def cached_map(n: int, args: argparse.Namespace) -> tuple[Path, dict[str, Any]]:
    """The map of ``n`` vertices under the cache, built if absent or unfinished."""
    root = args.cache / f"map-{n}-d{args.dim}-s{args.seq_len}-e{args.edge_every}-r{args.seed}"
    done = root / "built.json"
    if done.is_file():
        return root / "bench.map", json.loads(done.read_text())
    shutil.rmtree(root, ignore_errors=True)
    root.mkdir(parents=True)
    info = build(root / "bench.map", n, args)
    done.write_text(json.dumps(info))
    return root / "bench.map", info


def run_mode(mode: str, map_path: Path, out: Path) -> dict[str, Any]:
    """One export (or the baseline walk) in this process; its figures."""
    from sprint_map.map import SprintMap
    from sprint_map.storage.scan import MapScan

    sampler = AnonPeak()
    started = time.perf_counter()
    with SprintMap.open(map_path, readonly=True) as m:
        if mode == "baseline":
            with MapScan(m.store) as scan:
                frames = sum(len(pos) for _, pos in scan.positions() if pos is not None)
                edges = sum(1 for _ in scan.edges())
            result = {"nodes": frames, "edges": edges, "bytes": 0}
        else:
            if mode.startswith("graphml"):
                report = m.export_graphml(out / "map.graphml", mode.split("-")[1])
            elif mode == "csv":
                report = m.export_csv(out / "csv")
            else:
                report = m.export_geojson(out / "map.geojson")
            result = {"nodes": report.nodes, "edges": report.edges, "bytes": report.bytes}
    seconds = time.perf_counter() - started
    return {"mode": mode, "seconds": round(seconds, 2), **result,
            "peak_rss_mb": round(_status_kb("VmHWM") / 1024, 1),
            "peak_anon_mb": round(sampler.stop(), 1)}


def roundtrip(map_path: Path, graphml: Path) -> dict[str, Any]:
    """Read the vertex-level GraphML back with networkx; compare with the map's graph."""
    import networkx as nx

    from sprint_map.export.graphml import vertex_graph
    from sprint_map.map import SprintMap
    from sprint_map.storage.scan import MapScan

    sampler = AnonPeak()
    started = time.perf_counter()
    got = nx.read_graphml(graphml)
    read_s = time.perf_counter() - started
    reader_peak = _status_kb("VmHWM") / 1024
    anon = sampler.stop()
    with SprintMap.open(map_path, readonly=True) as m, MapScan(m.store) as scan:
        want = vertex_graph(scan)
    equal = (dict(got.nodes(data=True)) == dict(want.nodes(data=True))
             and {(u, v): d for u, v, d in got.edges(data=True)}
             == {(u, v): d for u, v, d in want.edges(data=True)}
             and all(got.graph[k] == v for k, v in want.graph.items()))
    return {"roundtrip": equal, "read_graphml_s": round(read_s, 2),
            "reader_peak_rss_mb": round(reader_peak, 1), "reader_peak_anon_mb": round(anon, 1),
            "nodes": got.number_of_nodes(), "edges": got.number_of_edges()}


def _child(args: list[str]) -> dict[str, Any]:
    out = subprocess.run([sys.executable, __file__, *args], check=True, capture_output=True,
                         text=True)
    result: dict[str, Any] = json.loads(out.stdout.strip().splitlines()[-1])
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--vertices", type=int, nargs="+", default=[100_000, 1_000_000])
    parser.add_argument("--dim", type=int, default=32)
    parser.add_argument("--seq-len", type=int, default=1000, help="frames per drive")
    parser.add_argument("--street-len", type=int, default=500)
    parser.add_argument("--revisits", type=int, default=5, help="drives per place, on average")
    parser.add_argument("--edge-every", type=int, default=10, help="an edge every n frames")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/sprint-export-bench"))
    parser.add_argument("--roundtrip-max", type=int, default=100_000)
    parser.add_argument("--json", type=Path)
    parser.add_argument("--run", choices=MODES, help=argparse.SUPPRESS)  # the fresh process
    parser.add_argument("--check", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--map", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.run:
        print(json.dumps(run_mode(args.run, args.map, args.out)))
        return 0
    if args.check:
        print(json.dumps(roundtrip(args.map, args.out / "map.graphml")))
        return 0
    rows = []
    print(f"{'vertices':>10} {'edges':>9} {'export':>17} {'seconds':>8} {'MB out':>8} "
          f"{'peak RSS MB':>11} {'peak anon MB':>12} {'peak/base':>9}", flush=True)
    for n in args.vertices:
        map_path, info = cached_map(n, args)
        out = args.cache / f"out-{n}"
        shutil.rmtree(out, ignore_errors=True)
        out.mkdir(parents=True)
        base = None
        for mode in MODES:
            row = {"vertices": info["vertices"], "map_edges": info["edges"],
                   **_child(["--run", mode, "--map", str(map_path), "--out", str(out)])}
            base = base or row
            row["peak_over_baseline"] = round(row["peak_rss_mb"] / base["peak_rss_mb"], 2)
            row["anon_over_baseline"] = round(row["peak_anon_mb"] / base["peak_anon_mb"], 2)
            rows.append(row)
            print(f"{row['vertices']:>10,} {row['map_edges']:>9,} {mode:>17} "
                  f"{row['seconds']:>8.1f} {row['bytes'] / 2**20:>8.1f} "
                  f"{row['peak_rss_mb']:>11.0f} {row['peak_anon_mb']:>12.0f} "
                  f"{row['peak_over_baseline']:>9.2f}", flush=True)
            if mode == "graphml-vertex" and n <= args.roundtrip_max:
                check = _child(["--check", "--map", str(map_path), "--out", str(out)])
                rows.append({"vertices": info["vertices"], "mode": "read_graphml", **check})
                print(f"{'':>10} read_graphml back: equal={check['roundtrip']} "
                      f"({check['nodes']:,} nodes, {check['edges']:,} edges) in "
                      f"{check['read_graphml_s']:.1f} s, reader peak RSS "
                      f"{check['reader_peak_rss_mb']:.0f} MB", flush=True)
                if not check["roundtrip"]:
                    print("GraphML round trip FAILED", file=sys.stderr)
                    return 1
        shutil.rmtree(out, ignore_errors=True)
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "args": {
            k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}},
            indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
