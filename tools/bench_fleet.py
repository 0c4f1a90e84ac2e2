"""Fleet benchmark (issue 16 item 4): the service batched vs one frame at a time, and
multi-drive ingest vs one drive per command, each against a baseline measured in the same run.

Service: a Nordland HoG map (the summer traversal's 3,576 frames; HoG of the images) served by
``sprint-map serve`` on loopback; 1, 16 and 64 simulated vehicles each stream their own stretch
of the winter traversal, one request in flight per vehicle, as raw float32 bodies (the fast
path), from one lean asyncio client (hand-written HTTP/1.1 keep-alive: a heavier client would
take the cores it measures). Each row reports frames/s, client-side p50/p99 latency, the
statuses seen, and whether every answer equals the offline ``localize`` of the same frames
(decision and probability). ``batched`` is the service's default (frames of all sessions
searched together, ``batch_window_ms`` 2, ``batch_max_frames`` 64); ``one-at-a-time`` turns
batching off (``batch_max_frames`` 0: each frame searched alone by a frame worker, as before).
An ``overload`` row drives 64 vehicles into a server that admits 32 frames at once: the excess
must be shed with 429/503, never a 5xx. The ratio column compares each row with the in-process
``Localizer.step`` loop measured in the same run.

Ingest: ten 1,000-frame drives of precomputed 256-dim descriptors: one ``ingest`` of all ten
against ten ``ingest`` calls (in process, and as CLI commands), appended (``--no-merge``, the
commit path alone: one group commit, ``sprint_map/storage/group_writer.py``) and localised
(merge). The appended rows are the median of ``--ingest-repeats`` runs (min and max shown).

Usage::

    python tools/bench_fleet.py                              # everything, Nordland
    python tools/bench_fleet.py --vehicles 16 --frames 200 --json fleet.json
    python tools/bench_fleet.py --skip-ingest --vehicles 1 16 64
    python tools/bench_fleet.py --skip-ingest --vehicles 16 --frames 100 --lag 10  # lagged sessions
    python tools/bench_fleet.py --skip-service --skip-localised --ingest-repeats 7
    python tools/bench_fleet.py --quick                      # a small synthetic map (tests)
    python tools/bench_fleet.py --skip-service --skip-ingest --ray   # tools/bench_ray.py only
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map.config import MapConfig
from sprint_map.map import SprintMap
from sprint_map.merge.drives import Drive

NORDLAND = Path(os.environ.get("SPRINT_MAP_NORDLAND", "/work/shared/data/nordland"))
CLI = [sys.executable, "-c", "from sprint_map.cli.main import main; main()"]


# --- the lean client ----------------------------------------------------------------------------
@dataclass
class Vehicle:
    """One simulated vehicle: its frames and what it measured."""

    index: int
    rows: np.ndarray
    #: The session's lag (``{"lag": L}``): answers name the frame they answer, L frames back.
    lag: int = 0
    answers: list[dict[str, Any]] = field(default_factory=list)
    latency_ms: list[float] = field(default_factory=list)
    statuses: dict[int, int] = field(default_factory=dict)
    error: str | None = None


async def _request(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, method: str,
                   path: str, body: bytes = b"", kind: str = "application/json"
                   ) -> tuple[int, bytes]:
    """One HTTP/1.1 request on a keep-alive connection: ``(status, body)``."""
    writer.write(f"{method} {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: {kind}\r\n"
                 f"Content-Length: {len(body)}\r\n\r\n".encode() + body)
    status_line = await reader.readline()
    if not status_line:
        raise ConnectionError("the server closed the connection")
    length = 0
    while (line := await reader.readline()) not in (b"\r\n", b"\n", b""):
        name, _, value = line.decode("latin-1").partition(":")
        if name.strip().lower() == "content-length":
            length = int(value)
    return int(status_line.split()[1]), await reader.readexactly(length)


async def _drive(v: Vehicle, host: str, port: int, opened: list[int], start: asyncio.Event,
                 deadline: float) -> None:
    try:
        reader, writer = await asyncio.open_connection(host, port)
        try:
            status, body = await _request(reader, writer, "POST", "/v1/sessions",
                                          json.dumps({"lag": v.lag} if v.lag else {}).encode())
            opened.append(status)
            if status != 201:
                v.error = f"session: HTTP {status} {body[:200]!r}"
                return
            path = f"/v1/sessions/{json.loads(body)['session_id']}/frames"
            await start.wait()
            for row in v.rows:
                if time.monotonic() >= deadline:  # bounded run: the rest is not sent
                    break
                frame = row.astype("<f4").tobytes()
                while True:
                    t0 = time.perf_counter()
                    status, body = await _request(reader, writer, "POST", path, frame,
                                                  "application/octet-stream")
                    v.latency_ms.append((time.perf_counter() - t0) * 1e3)
                    v.statuses[status] = v.statuses.get(status, 0) + 1
                    if status not in (429, 503) or time.monotonic() >= deadline:
                        break
                    await asyncio.sleep(0.02)  # shed: back off, send the same frame again
                if status != 200:
                    if status not in (429, 503):
                        v.error = f"HTTP {status}: {body[:200]!r}"
                    return
                v.answers.append(json.loads(body))
            await _request(reader, writer, "DELETE", path.rsplit("/", 1)[0])
        finally:
            writer.close()
    except Exception as exc:  # reported in the table, never hidden
        opened.append(0)
        v.error = f"{type(exc).__name__}: {exc}"


async def _fleet(vehicles: list[Vehicle], host: str, port: int, duration: float) -> float:
    opened: list[int] = []
    start = asyncio.Event()
    deadline = time.monotonic() + duration
    tasks = [asyncio.create_task(_drive(v, host, port, opened, start, deadline))
             for v in vehicles]
    while len(opened) < len(vehicles):  # every session open before the first frame
        await asyncio.sleep(0.01)
    t0 = time.perf_counter()
    start.set()
    await asyncio.gather(*tasks)
    return time.perf_counter() - t0


def drive_fleet(vehicles: list[Vehicle], url: str, duration: float) -> float:
    """All vehicles at once against ``url``; the wall time of their frames."""
    host, port = url.split("://", 1)[1].rstrip("/").rsplit(":", 1)
    return asyncio.run(_fleet(vehicles, host, int(port), duration))


# --- service ------------------------------------------------------------------------------------
def start_server(map_path: Path, config: dict[str, Any], log: Path
                 ) -> tuple[subprocess.Popen[str], str]:
    conf = log.with_suffix(".json")
    conf.write_text(json.dumps({"max_sessions": 1024, "max_pending_frames": 4, **config}))
    proc = subprocess.Popen([*CLI, "serve", str(map_path), "--port", "0", "--config",
                             str(conf)], stdout=subprocess.PIPE, stderr=log.open("w"), text=True)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if not line.startswith("serving "):
        raise SystemExit(f"server did not start: {line!r} {log.read_text()}")
    url = line.split(" on ", 1)[1].strip()
    import httpx

    for _ in range(2400):
        try:
            if httpx.get(f"{url}/readyz").status_code == 200:
                return proc, url
        except httpx.TransportError:
            pass
        time.sleep(0.05)
    raise SystemExit(f"server not ready: {log.read_text()}")


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of process ``pid`` so far (Linux ``/proc``; 0 elsewhere)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def stop_server(proc: subprocess.Popen[str]) -> int:
    proc.send_signal(signal.SIGTERM)
    return proc.wait(120)


def make_vehicles(n: int, frames: int, rows: np.ndarray, lag: int = 0) -> list[Vehicle]:
    """Vehicle i drives ``frames`` consecutive frames from offset ``i * (len - frames) / n``."""
    frames = min(frames, len(rows))
    span = max(len(rows) - frames, 0)
    return [Vehicle(i, rows[span * i // max(n, 1):][:frames], lag=lag) for i in range(n)]


def offline_equal(map_path: Path, vehicles: list[Vehicle]) -> dict[str, int]:
    """Frames whose answer equals the offline ``localize`` of the same frames (the place and
    the probability, as the answer rounds it); with a lag, ``localize --lag`` of the frames
    posted, for the frames answered (the last ``lag`` are answered by a commit, not sent)."""
    same = frames = 0
    with SprintMap.open(map_path, readonly=True) as m:
        for v in vehicles:
            if v.answers:
                found, _ = m.localize(v.rows[: len(v.answers)], lag=v.lag)
                answered = [a for a in v.answers if a["frame"] is not None]
                for a in answered:
                    frames += 1
                    mine = found[a["frame"]].to_dict()  # the same fields, bit for bit
                    same += all(mine[key] == a[key]
                                for key in ("frame", "seq_id", "image_id", "prob"))
    return {"frames": frames, "equal": same}


def baseline(map_path: Path, rows: np.ndarray, lag: int = 0) -> float:
    """Frames/s of ``Localizer.step`` (with a lag: ``LaggedLocalizer.step``) in process, one
    frame at a time, no HTTP."""
    from sprint_map.localize.lagged import LaggedLocalizer

    with SprintMap.open(map_path, readonly=True) as m:
        localizer = LaggedLocalizer(m, lag)
        localizer.step(rows[0])
        t0 = time.perf_counter()
        for row in rows:
            localizer.step(row)
        return len(rows) / (time.perf_counter() - t0)


def service_row(mode: str, n: int, vehicles: list[Vehicle], seconds: float,
                base_fps: float, check: dict[str, int]) -> dict[str, Any]:
    lat = [x for v in vehicles for x in v.latency_ms]
    served = sum(len(v.answers) for v in vehicles)
    statuses: dict[str, int] = {}
    for v in vehicles:
        for code, count in v.statuses.items():
            statuses[str(code)] = statuses.get(str(code), 0) + count
    fps = served / seconds if seconds else 0.0
    return {"mode": mode, "vehicles": n, "frames": served, "seconds": round(seconds, 3),
            "frames_per_s": round(fps, 1),
            "p50_ms": round(float(np.percentile(lat, 50)), 2) if lat else None,
            "p99_ms": round(float(np.percentile(lat, 99)), 2) if lat else None,
            "vs_step": round(fps / base_fps, 2), "statuses": statuses,
            "errors": sum(v.error is not None for v in vehicles),
            "first_error": next((v.error for v in vehicles if v.error), None),
            "offline_equal": f"{check['equal']}/{check['frames']}"}


def bench_service(map_path: Path, rows: np.ndarray, args: argparse.Namespace, work: Path
                  ) -> tuple[list[dict[str, Any]], float]:
    base_fps = baseline(map_path, rows[: args.frames], args.lag)
    modes = [("batched", {}), ("one-at-a-time", {"batch_max_frames": 0})]
    runs = [(mode, conf, n) for mode, conf in modes for n in args.vehicles]
    if args.overload:
        runs.append(("overload (32 admitted)", {"max_queued_frames": 32}, args.overload))
    out = []
    for mode, conf, n in runs:
        proc, url = start_server(map_path, conf, work / f"serve-{len(out)}.log")
        try:
            vehicles = make_vehicles(n, args.frames, rows, args.lag)
            cpu0, client0 = cpu_seconds(proc.pid), time.process_time()
            seconds = drive_fleet(vehicles, url, args.duration)
            cpu1, client1 = cpu_seconds(proc.pid), time.process_time()
        finally:
            code = stop_server(proc)
        row = service_row(mode, n, vehicles, seconds, base_fps, offline_equal(map_path,
                                                                              vehicles))
        row["server_exit"] = code
        served = max(row["frames"], 1)
        # CPU per frame: what the load on the machine does not change much (wall time does)
        row["server_cpu_ms"] = round((cpu1 - cpu0) / served * 1e3, 3)
        row["client_cpu_ms"] = round((client1 - client0) / served * 1e3, 3)
        out.append(row)
        print(f"  {mode}, {n} vehicles: {row['frames_per_s']} frames/s, p99 "
              f"{row['p99_ms']} ms", file=sys.stderr)
    return out, base_fps


def build_nordland(work: Path, quick: bool) -> tuple[Path, np.ndarray]:
    """The served map and the query rows: Nordland HoG (summer map, winter queries), or with
    ``quick`` a small synthetic map of 64-dim descriptors."""
    path = work / "fleet.map"
    if quick or not NORDLAND.is_dir():
        rng = np.random.default_rng(0)
        places = rng.standard_normal((600, 64)).astype(np.float32)
        with SprintMap.create(path, MapConfig(dim=64)) as m:
            m.ingest(places, name="map", merge=False)
        return path, (places + 0.2 * rng.standard_normal(places.shape)).astype(np.float32)
    from sprint_map.frontend.descriptors import DescriptorSpec
    from sprint_map.frontend.sources import open_source

    with SprintMap.create(path, MapConfig.for_descriptor("hog")) as m:
        m.ingest(m.open_source(NORDLAND / "summer").iter_batches(), name="summer")
    return path, open_source(NORDLAND / "winter", DescriptorSpec("hog")).read_all()


# --- ingest -------------------------------------------------------------------------------------
def bench_ingest(work: Path, drives: int, frames: int, dim: int, repeats: int = 5,
                 localised: bool = True) -> list[dict[str, Any]]:
    """Ten drives (``drives`` of ``frames``) in one ingest vs one ingest per drive, appended and
    localised, in process and as CLI commands. Appended rows are measured ``repeats`` times
    each, one call and ten calls alternating, each on a fresh map: the median is reported with
    the min and max (a 10k-frame commit takes tens of ms, and the disk is shared)."""
    rng = np.random.default_rng(1)
    places = rng.standard_normal((frames, dim)).astype(np.float32)
    data = [(places + 0.3 * rng.standard_normal(places.shape)).astype(np.float32)
            for _ in range(drives)]
    files = []
    for i, d in enumerate(data):
        files.append(work / f"drive{i}.npy")
        np.save(files[-1], d)
    total = drives * frames
    out: list[dict[str, Any]] = []

    def rows(what: str, times: dict[str, list[float]], base: str) -> None:
        for how, runs in times.items():
            seconds = float(np.median(runs))
            out.append({"what": what, "how": how, "drives": drives, "frames": total,
                        "runs": len(runs), "seconds": round(seconds, 4),
                        "min_s": round(min(runs), 4), "max_s": round(max(runs), 4),
                        "frames_per_s": round(total / seconds),
                        "vs_one_per_drive": round(float(np.median(times[base])) / seconds,
                                                  2)})

    for merge in (False, True) if localised else (False,):
        label = "localised + merged" if merge else "appended (--no-merge)"
        times: dict[str, list[float]] = {"one ingest of all": [], "one ingest per drive": []}
        for run in range(1 if merge else repeats):
            for n, how in enumerate(times):
                path = work / f"ingest-{merge}-{run}-{n}.map"
                with SprintMap.create(path, MapConfig(dim=dim)) as m:
                    m.add_sequence(places, name="base")  # a map to localise against
                    t0 = time.perf_counter()
                    if how == "one ingest of all":
                        m.ingest_drives([Drive(d, f"d{i}") for i, d in enumerate(data)],
                                        merge=merge)
                    else:
                        for i, d in enumerate(data):
                            m.ingest(d, name=f"d{i}", merge=merge)
                    times[how].append(time.perf_counter() - t0)
                shutil.rmtree(path)
        rows(f"in process, {label}", times, "one ingest per drive")
        # The same as commands: one process for all drives, or one process per drive.
        flag = [] if merge else ["--no-merge"]
        cli_times: dict[str, list[float]] = {"one command, all drives": [],
                                             "one command per drive": []}
        for run in range(1 if merge else max(1, repeats // 2)):
            for n, how in enumerate(cli_times):
                path = work / f"cli-{merge}-{run}-{n}.map"
                subprocess.run([*CLI, "init", str(path), "--dim", str(dim)], check=True,
                               capture_output=True)
                t0 = time.perf_counter()
                if how == "one command, all drives":
                    subprocess.run([*CLI, "ingest", str(path), *map(str, files), *flag, "-q"],
                                   check=True, capture_output=True)
                else:
                    for f in files:
                        subprocess.run([*CLI, "ingest", str(path), str(f), *flag, "-q"],
                                       check=True, capture_output=True)
                cli_times[how].append(time.perf_counter() - t0)
                shutil.rmtree(path)
        rows(f"CLI wall time, {label}", cli_times, "one command per drive")
    return out


def table(rows: list[dict[str, Any]], head: tuple[str, ...]) -> str:
    lines = [" | ".join(head), " | ".join("---" for _ in head)]
    lines += [" | ".join(str(r.get(k)) for k in head) for r in rows]
    return "\n".join(lines)


def run_bench_ray(work: Path, quick: bool) -> dict[str, Any]:
    """tools/bench_ray.py's sections (it prints its own tables); its JSON."""
    from tools import bench_ray
    out = work / "ray.json"
    bench_ray.main(["--json", str(out), *(["--quick"] if quick else [])])
    data: dict[str, Any] = json.loads(out.read_text())
    return data


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--vehicles", type=int, nargs="+", default=[1, 16, 64])
    parser.add_argument("--frames", type=int, default=200, help="Frames per vehicle.")
    parser.add_argument("--duration", type=float, default=120.0, help="Seconds per run (bound).")
    parser.add_argument("--overload", type=int, default=64,
                        help="Vehicles of the overload row (0: none).")
    parser.add_argument("--drives", type=int, default=10)
    parser.add_argument("--drive-frames", type=int, default=1000)
    parser.add_argument("--dim", type=int, default=256, help="Ingest descriptors' dimension.")
    parser.add_argument("--ingest-repeats", type=int, default=5,
                        help="Runs of each appended ingest row (median, min, max reported).")
    parser.add_argument("--skip-localised", action="store_true",
                        help="Ingest: only the appended (--no-merge) rows (seconds, not minutes).")
    parser.add_argument("--skip-service", action="store_true")
    parser.add_argument("--skip-ingest", action="store_true")
    parser.add_argument("--quick", action="store_true", help="A small synthetic map.")
    parser.add_argument("--ray", action="store_true",
                        help="Also the Ray sections (tools/bench_ray.py: the ingest farm vs "
                        "serial ingest, a search fanned out to shards vs in process, the "
                        "per-segment figures; needs the ray extra).")
    parser.add_argument("--lag", type=int, default=0,
                        help="Sessions answer each frame L frames late ({\"lag\": L}); the "
                        "baseline is LaggedLocalizer.step with the same lag.")
    parser.add_argument("--json", type=Path, help="Write the results here.")
    args = parser.parse_args(argv)

    result: dict[str, Any] = {"args": {k: str(v) for k, v in vars(args).items()},
                              "load_average": os.getloadavg()}
    ok = True
    with tempfile.TemporaryDirectory(prefix="bench-fleet-") as tmp:
        work = Path(tmp)
        if not args.skip_service:
            map_path, rows = build_nordland(work, args.quick)
            service, base_fps = bench_service(map_path, rows, args, work)
            result["service"] = service
            result["step_frames_per_s"] = round(base_fps, 1)
            print(f"in-process Localizer.step, same run: {base_fps:.1f} frames/s")
            print(table(service, ("mode", "vehicles", "frames", "frames_per_s", "p50_ms",
                                  "p99_ms", "vs_step", "server_cpu_ms", "client_cpu_ms",
                                  "statuses", "errors", "offline_equal")))
            for r in service:
                five = sum(n for code, n in r["statuses"].items() if code.startswith("5")
                           and code != "503")
                overload = r["mode"].startswith("overload")
                ok &= five == 0 and r["server_exit"] == 0
                ok &= overload or (r["errors"] == 0 and r["offline_equal"].split("/")[0]
                                   == r["offline_equal"].split("/")[1])
                if r["first_error"]:
                    print(f"{r['mode']}, {r['vehicles']} vehicles: {r['first_error']}")
        if not args.skip_ingest:
            ingest = bench_ingest(work, args.drives, args.drive_frames, args.dim,
                                  args.ingest_repeats, not args.skip_localised)
            result["ingest"] = ingest
            print(table(ingest, ("what", "how", "drives", "frames", "runs", "seconds", "min_s",
                                 "max_s", "frames_per_s", "vs_one_per_drive")))
        if args.ray:
            result["ray"] = run_bench_ray(work, args.quick)
    result["load_average_after"] = os.getloadavg()
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
