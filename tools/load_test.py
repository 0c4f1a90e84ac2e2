"""Load test of ``sprint-map serve``: N simulated vehicles replay traversals concurrently.

Each vehicle opens a session and streams its own stretch of a query traversal, frame by frame
(one request in flight per vehicle, as a camera would), against a real server on loopback.
Reports frames/s and per-frame latency (client side: request to answer) in a table, beside the
baseline of the same frames localised in process without HTTP (``Localizer.step``, one
thread), and checks that the answers equal the offline ``localize`` of the same frames (no
commit runs during the load, so the map does not change).

Usage::

    python tools/load_test.py                          # Nordland summer map, winter queries
    python tools/load_test.py --vehicles 1 4 16 --frames 200 --json load.json
    python tools/load_test.py --data city              # the synthetic city (2 traversals)
    python tools/load_test.py --images                 # send PNG bytes; the server describes
    python tools/load_test.py --binary                 # raw float32 bodies, no JSON
    python tools/load_test.py --map city.map --queries drive.npy

Bounded: at most ``--frames`` per vehicle and ``--duration`` seconds per run.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from sprint_map.config import MapConfig
from sprint_map.frontend.descriptors import DescriptorSpec
from sprint_map.frontend.imagefiles import list_images
from sprint_map.frontend.sources import open_source
from sprint_map.map import SprintMap

NORDLAND = Path(os.environ.get("SPRINT_MAP_NORDLAND", "/work/shared/data/nordland"))
SERVE = [sys.executable, "-c", "from sprint_map.cli.main import main; main()", "serve"]


@dataclass
class Vehicle:
    """One simulated vehicle: its frames (request bodies) and what it measured."""

    index: int
    offset: int
    rows: np.ndarray
    bodies: list[bytes]
    content_type: str
    answers: list[dict[str, Any]] = field(default_factory=list)
    latency_ms: list[float] = field(default_factory=list)
    error: str | None = None

    def drive(self, url: str, deadline: float, start: threading.Barrier) -> None:
        try:
            with httpx.Client(base_url=url, timeout=60) as client:
                sid = client.post("/v1/sessions").json()["session_id"]
                path = f"/v1/sessions/{sid}/frames"
                headers = {"content-type": self.content_type}
                start.wait()
                for body in self.bodies:
                    if time.monotonic() > deadline:
                        break
                    t0 = time.perf_counter()
                    response = client.post(path, content=body, headers=headers)
                    self.latency_ms.append((time.perf_counter() - t0) * 1e3)
                    if response.status_code != 200:
                        self.error = f"HTTP {response.status_code}: {response.text}"
                        return
                    self.answers.append(response.json())
                client.delete(f"/v1/sessions/{sid}")
        except Exception as exc:  # reported in the table, never hidden
            self.error = f"{type(exc).__name__}: {exc}"


def build_inputs(args: argparse.Namespace, work: Path) -> tuple[Path, np.ndarray, list[Path]]:
    """The map to serve, the query descriptors and (for --images) the query image files."""
    if args.map:
        if args.queries is None:
            raise SystemExit("--map needs --queries (a .npy of descriptors)")
        return args.map, np.load(args.queries).astype(np.float32), []
    if args.data == "nordland":
        database, query = NORDLAND / "summer", NORDLAND / "winter"
    else:
        from sprint_map.synth import generate_city

        city = generate_city(work / "city", 2, args.city_frames, seed=args.seed)
        database, query = sorted(p for p in city.iterdir() if p.is_dir())[:2]
    map_path = work / "load.map"
    with SprintMap.create(map_path, MapConfig.for_descriptor("hog")) as m:
        m.ingest(m.open_source(database).iter_batches(), name=database.name)
    rows = open_source(query, DescriptorSpec("hog")).read_all()
    return map_path, rows, list_images(query)


def start_server(map_path: Path, workers: int, log: Path) -> tuple[subprocess.Popen[str], str]:
    config = log.with_suffix(".json")
    config.write_text(json.dumps({"frame_workers": workers, "max_sessions": 1024,
                                  "max_pending_frames": 4}))
    proc = subprocess.Popen([*SERVE, str(map_path), "--port", "0", "--config", str(config)],
                            stdout=subprocess.PIPE, stderr=log.open("w"), text=True)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if not line.startswith("serving "):
        raise SystemExit(f"server did not start: {line!r} {log.read_text()}")
    url = line.split(" on ", 1)[1].strip()
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"{url}/readyz").status_code == 200:
                return proc, url
        except httpx.TransportError:
            pass
        time.sleep(0.05)
    raise SystemExit(f"server not ready: {log.read_text()}")


def make_vehicles(n: int, frames: int, rows: np.ndarray, images: list[Path], use_images: bool,
                  binary: bool = False) -> list[Vehicle]:
    """Vehicle i drives ``frames`` frames from offset ``i * (len - frames) / n``."""
    frames = min(frames, len(rows))
    span = max(len(rows) - frames, 0)
    out = []
    for i in range(n):
        offset = span * i // max(n, 1)
        mine = rows[offset : offset + frames]
        if use_images:
            bodies = [images[offset + j].read_bytes() for j in range(len(mine))]
            kind = "image/png"
        elif binary:
            bodies = [r.astype("<f4").tobytes() for r in mine]
            kind = "application/octet-stream"
        else:
            bodies = [json.dumps({"descriptor": r.tolist()}).encode() for r in mine]
            kind = "application/json"
        out.append(Vehicle(i, offset, mine, bodies, kind))
    return out


def run_load(url: str, vehicles: list[Vehicle], duration: float) -> float:
    start = threading.Barrier(len(vehicles) + 1)
    deadline = time.monotonic() + duration
    threads = [threading.Thread(target=v.drive, args=(url, deadline, start)) for v in vehicles]
    for t in threads:
        t.start()
    start.wait()
    t0 = time.perf_counter()
    for t in threads:
        t.join()
    return time.perf_counter() - t0


def offline_check(map_path: Path, vehicles: list[Vehicle]) -> dict[str, Any]:
    """Compare every answer with the offline ``localize`` of the same frames (prefix)."""
    same = frames = 0
    worst = 0.0
    with SprintMap.open(map_path, readonly=True) as m:
        for v in vehicles:
            if not v.answers:
                continue
            found, _ = m.localize(v.rows[: len(v.answers)])
            for d, a in zip(found, v.answers, strict=True):
                frames += 1
                same += (d.seq_id, d.image_id) == (a["seq_id"], a["image_id"])
                worst = max(worst, abs(d.prob - a["prob"]))
    return {"frames": frames, "equal": same, "max_prob_diff": worst}


def baseline(map_path: Path, rows: np.ndarray) -> dict[str, Any]:
    """The same frames localised in process, one ``Localizer.step`` at a time, no HTTP."""
    with SprintMap.open(map_path, readonly=True) as m:
        localizer = m.localizer()
        lat = []
        t0 = time.perf_counter()
        for row in rows:
            s = time.perf_counter()
            localizer.step(row)
            lat.append((time.perf_counter() - s) * 1e3)
        wall = time.perf_counter() - t0
    return {"frames": len(rows), "seconds": wall, "lat": lat}


def row(name: str, vehicles: int, frames: int, seconds: float, lat: list[float],
        base_fps: float | None) -> dict[str, Any]:
    fps = frames / seconds if seconds else 0.0
    return {"mode": name, "vehicles": vehicles, "frames": frames, "seconds": round(seconds, 3),
            "frames_per_s": round(fps, 1),
            "p50_ms": round(float(np.percentile(lat, 50)), 3) if lat else None,
            "p99_ms": round(float(np.percentile(lat, 99)), 3) if lat else None,
            "vs_baseline": round(fps / base_fps, 3) if base_fps else 1.0}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", choices=["nordland", "city"],
                        default="nordland" if NORDLAND.is_dir() else "city")
    parser.add_argument("--map", type=Path, help="Serve this map (with --queries).")
    parser.add_argument("--queries", type=Path, help=".npy of query descriptors for --map.")
    parser.add_argument("--vehicles", type=int, nargs="+", default=[16])
    parser.add_argument("--frames", type=int, default=200, help="Frames per vehicle (bound).")
    parser.add_argument("--duration", type=float, default=120.0, help="Seconds per run (bound).")
    parser.add_argument("--workers", type=int, default=4, help="Server frame workers.")
    parser.add_argument("--images", action="store_true", help="Send PNG bytes, not descriptors.")
    parser.add_argument("--binary", action="store_true",
                        help="Send descriptors as raw float32 (application/octet-stream), not JSON.")
    parser.add_argument("--city-frames", type=int, default=400)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, help="Write the results here.")
    args = parser.parse_args(argv)
    if args.images and args.map:
        raise SystemExit("--images needs --data (image folders), not --map")

    with tempfile.TemporaryDirectory(prefix="load-test-") as tmp:
        work = Path(tmp)
        t0 = time.perf_counter()
        map_path, rows, images = build_inputs(args, work)
        print(f"map {map_path} ({args.data if not args.map else 'given'}), {len(rows)} query "
              f"frames; inputs ready in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        frames = min(args.frames, len(rows))
        base = baseline(map_path, rows[:frames])
        base_fps = base["frames"] / base["seconds"]
        rows_out = [row("in-process Localizer.step (baseline)", 1, base["frames"],
                        base["seconds"], base["lat"], None)]
        checks = []
        proc, url = start_server(map_path, args.workers, work / "server.log")
        try:
            for n in args.vehicles:
                vehicles = make_vehicles(n, frames, rows, images, args.images, args.binary)
                seconds = run_load(url, vehicles, args.duration)
                errors = [v.error for v in vehicles if v.error]
                if errors:
                    print(f"errors ({len(errors)} vehicles): {errors[0]}", file=sys.stderr)
                lat = [x for v in vehicles for x in v.latency_ms]
                served = sum(len(v.answers) for v in vehicles)
                kind = ("PNG images" if args.images else "float32 descriptors" if args.binary
                        else "JSON descriptors")
                mode = f"serve, {kind}"
                rows_out.append(row(mode, n, served, seconds, lat, base_fps))
                server_ms = [a["timing"]["server_ms"] for v in vehicles for a in v.answers]
                rows_out[-1]["server_p50_ms"] = round(float(np.percentile(server_ms, 50)), 3)
                rows_out[-1]["errors"] = len(errors)
                checks.append({"vehicles": n, **offline_check(map_path, vehicles)})
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(60)

    head = ("mode", "vehicles", "frames", "seconds", "frames_per_s", "p50_ms", "p99_ms",
            "vs_baseline")
    print(" | ".join(head))
    print(" | ".join("---" for _ in head))
    for r in rows_out:
        print(" | ".join(str(r[k]) for k in head))
    ok = True
    for c in checks:
        equal = c["equal"] == c["frames"]
        ok &= equal
        print(f"offline localize check, {c['vehicles']} vehicles: {c['equal']}/{c['frames']} "
              f"frames with the same decision, max |prob diff| {c['max_prob_diff']:.2e}"
              f"{'' if equal else '  MISMATCH'}")
    if args.json:
        args.json.write_text(json.dumps({"rows": rows_out, "offline_check": checks,
                                         "args": {k: str(v) for k, v in vars(args).items()}},
                                        indent=1))
    return 0 if ok and all(r.get("errors", 0) == 0 for r in rows_out) else 1


if __name__ == "__main__":
    sys.exit(main())
