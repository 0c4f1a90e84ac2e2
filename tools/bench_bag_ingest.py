"""Bag ingest rate against the same frames as an image folder, and its memory in the bag's length.

Makes ``--frames`` camera frames (crops sliding along a textured panorama, ``--size`` W x H,
JPEG quality 85) and writes the same JPEG bytes twice: as an image folder and as a bag
(``--kind``: ``ros1`` ``.bag``, ``ros2-mcap``, ``ros2-sqlite3`` or a bare ``mcap``) with a
``sensor_msgs/CompressedImage`` topic at 10 Hz and a ``sensor_msgs/NavSatFix`` topic at 10 Hz
(a drive north at 10 m/s). Each is then ingested into a fresh HoG map by ``sprint-map ingest``
in its own process (the folder first: the baseline), and for each the wall time, frames/s and
the process's peak RSS are reported; the bag's rate over the folder's is the target's ratio
(>= 0.9). With ``--memory-frames M`` a bag of M frames is ingested too, to compare peak RSS
across lengths (streamed: it should not grow with the bag).

    python tools/bench_bag_ingest.py --frames 10000 --memory-frames 2500 --json bag.json
    python tools/bench_bag_ingest.py --frames 500 --kind mcap      # smoke run
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

T0 = 1_700_000_000 * 10**9


def make_frames(n: int, width: int, height: int, seed: int) -> list[bytes]:
    """``n`` JPEG frames sliding 3 px a frame along a smooth random panorama."""
    rng = np.random.default_rng(seed)
    pano_w = width + 3 * n
    coarse = rng.integers(0, 256, (height // 8, pano_w // 8 + 1, 3), dtype=np.uint8)
    pano = cv2.resize(coarse, (pano_w, height), interpolation=cv2.INTER_CUBIC)
    out = []
    for i in range(n):
        ok, data = cv2.imencode(".jpg", pano[:, 3 * i: 3 * i + width],
                                [cv2.IMWRITE_JPEG_QUALITY, 85])
        assert ok
        out.append(data.tobytes())
    return out


def write_folder(folder: Path, frames: list[bytes]) -> Path:
    folder.mkdir(parents=True)
    for i, data in enumerate(frames):
        (folder / f"{i:06d}.jpg").write_bytes(data)
    return folder


def write_bag(path: Path, kind: str, frames: list[bytes]) -> Path:
    """A bag of ``frames`` at 10 Hz with NavSatFix at 10 Hz (offset 50 ms), via rosbags."""
    from rosbags.typesys import Stores, get_typestore

    ros1 = kind == "ros1"
    ts = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    Header, Time = ts.types["std_msgs/msg/Header"], ts.types["builtin_interfaces/msg/Time"]
    Image, Fix = ts.types["sensor_msgs/msg/CompressedImage"], ts.types["sensor_msgs/msg/NavSatFix"]
    Status = ts.types["sensor_msgs/msg/NavSatStatus"]

    def header(t: int) -> Any:
        stamp = Time(sec=t // 10**9, nanosec=t % 10**9)
        return Header(seq=0, stamp=stamp, frame_id="x") if ros1 else Header(stamp=stamp,
                                                                             frame_id="x")

    serialize = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    cov = np.array([4.0, 0, 0, 0, 4.0, 0, 0, 0, 9.0])

    def records(conn_img: Any, conn_fix: Any) -> Any:
        for i, data in enumerate(frames):
            t = T0 + i * 100_000_000
            yield conn_fix, t - 50_000_000, serialize(Fix(
                header=header(t), status=Status(status=0, service=1),
                latitude=59.9 + i * 1.0 / 111_320.0, longitude=10.7, altitude=0.0,
                position_covariance=cov, position_covariance_type=2), "sensor_msgs/msg/NavSatFix")
            yield conn_img, t, serialize(Image(header=header(t), format="jpeg",
                                               data=np.frombuffer(data, np.uint8)),
                                         "sensor_msgs/msg/CompressedImage")

    if ros1:
        from rosbags.rosbag1 import Writer as Writer1

        path = path.with_suffix(".bag")
        with Writer1(path) as writer:
            img = writer.add_connection("/cam", "sensor_msgs/msg/CompressedImage", typestore=ts)
            fix = writer.add_connection("/fix", "sensor_msgs/msg/NavSatFix", typestore=ts)
            for conn, t, raw in records(img, fix):
                writer.write(conn, t, raw)
        return path
    from rosbags.rosbag2 import StoragePlugin, Writer

    folder = path if kind != "mcap" else path.with_name(path.name + "-dir")
    plugin = StoragePlugin.SQLITE3 if kind == "ros2-sqlite3" else StoragePlugin.MCAP
    with Writer(folder, version=9, storage_plugin=plugin) as writer2:
        img = writer2.add_connection("/cam", "sensor_msgs/msg/CompressedImage", typestore=ts)
        fix = writer2.add_connection("/fix", "sensor_msgs/msg/NavSatFix", typestore=ts)
        for conn, t, raw in records(img, fix):
            writer2.write(conn, t, raw)
    if kind != "mcap":
        return folder
    (found,) = folder.glob("*.mcap")
    target = path.with_suffix(".mcap")
    shutil.move(found, target)
    shutil.rmtree(folder)
    return target


#: The CLI in a fresh process that reports its own peak RSS (``VmHWM``, which exec resets;
#: ``getrusage`` would count the pages of the benchmark it was forked from) on stderr.
CLI = """
import atexit, sys
def _peak():
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            sys.stderr.write("VmHWM " + line.split()[1] + "\\n")
atexit.register(_peak)
from sprint_map.cli.main import main
main()
"""


def run_measured(work: Path, source: Path, label: str) -> dict[str, Any]:
    """``sprint-map ingest`` into a fresh HoG map in its own process: seconds, frames/s and
    the process's peak RSS."""
    map_dir = work / f"map-{label}"
    shutil.rmtree(map_dir, ignore_errors=True)
    cli = [sys.executable, "-c", CLI]
    subprocess.run([*cli, "init", str(map_dir), "--descriptor", "hog"], check=True,
                   capture_output=True)
    started = time.perf_counter()
    done = subprocess.run([*cli, "ingest", str(map_dir), str(source), "--quiet", "--json"],
                          capture_output=True, text=True)
    seconds = time.perf_counter() - started
    if done.returncode:
        raise SystemExit(f"{label}: ingest failed: {done.stderr.strip()}")
    peak_kb = int(done.stderr.split("VmHWM ")[-1].split()[0])
    frames = json.loads(done.stdout)["frames"]
    return {"source": label, "frames": frames, "seconds": round(seconds, 2),
            "frames_per_s": round(frames / seconds, 1), "peak_rss_mb": round(peak_kb / 1024, 1)}


def best_of(work: Path, sources: list[tuple[Path, str]], repeat: int) -> list[dict[str, Any]]:
    """Each source ingested ``repeat`` times, the sources alternating (a shared machine's load
    then weighs on both alike); the fastest run of each, with every run's seconds."""
    runs: dict[str, list[dict[str, Any]]] = {label: [] for _, label in sources}
    for _ in range(repeat):
        for source, label in sources:
            runs[label].append(run_measured(work, source, label))
    out = []
    for rows in runs.values():
        best = min(rows, key=lambda r: r["seconds"])
        out.append({**best, "runs_s": [r["seconds"] for r in rows],
                    "peak_rss_mb": max(r["peak_rss_mb"] for r in rows)})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=10000)
    parser.add_argument("--memory-frames", type=int, default=0,
                        help="Also ingest a bag of this many frames (peak RSS by length).")
    parser.add_argument("--size", default="640x480", help="Frame size W x H.")
    parser.add_argument("--kind", default="ros1",
                        choices=["ros1", "ros2-mcap", "ros2-sqlite3", "mcap"])
    parser.add_argument("--repeat", type=int, default=2,
                        help="Runs of each source, alternating; the fastest is reported.")
    parser.add_argument("--work", type=Path, default=Path("/tmp/sprint-bag-bench"))
    parser.add_argument("--json", type=Path, help="Also write the results here.")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    shutil.rmtree(args.work, ignore_errors=True)
    args.work.mkdir(parents=True)
    frames = make_frames(args.frames, width, height, seed=0)
    folder = write_folder(args.work / "folder", frames)
    bag = write_bag(args.work / "drive", args.kind, frames)
    small = (write_bag(args.work / "small", args.kind, frames[: args.memory_frames])
             if args.memory_frames else None)
    del frames
    rows = best_of(args.work, [(folder, "image folder"), (bag, f"{args.kind} bag")],
                   args.repeat)
    if small is not None:
        rows.append(run_measured(args.work, small, f"{args.kind} bag (short)"))
    ratio = rows[1]["frames_per_s"] / rows[0]["frames_per_s"]
    print(f"{args.frames} frames {width}x{height} JPEG, GNSS 10 Hz, {os.cpu_count()} cores, "
          f"load {os.getloadavg()[0]:.1f}")
    print("| source | frames | s (best; all runs) | frames/s | peak RSS MB |\n|---|---|---|---|---|")
    for r in rows:
        runs = ", ".join(str(v) for v in r.get("runs_s", [r["seconds"]]))
        print(f"| {r['source']} | {r['frames']} | {r['seconds']} ({runs}) | "
              f"{r['frames_per_s']} | {r['peak_rss_mb']} |")
    print(f"bag / folder frame rate: {ratio:.3f} (target >= 0.9)")
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "ratio": round(ratio, 3),
                                         "size": args.size, "kind": args.kind}, indent=2) + "\n")


if __name__ == "__main__":
    main()
