"""Viewer benchmark: first paint and payload sizes of ``sprint-map view`` on a large map.

Builds a synthetic map of ``--vertices`` vertices with positions (drives along the streets of
a generated city, each street driven several times, every ``--edge-every`` frames of a drive
joined both ways to the previous drive of its street, as merges add them), records a trace of
a drive localised against it, then starts a real ``sprint-map view`` process (which summarises
the map before announcing itself) and opens the page ``--runs`` times in Debian's Chromium
(Selenium; the harness of the browser tests, ``tests.helpers.browser``), measuring:

* ``summarise_s``: the view process from start to its announcement (open, overview computed);
* ``first_paint_ms`` / ``first_contentful_paint_ms``: the browser's paint timing entries;
* ``overview_drawn_ms``: navigation start to the overview's canvas drawn with every drive
  (the page's ``performance.mark("overview-drawn")``): the figure the target is about;
* ``redraw_ms``: one redraw of the overview in the page (what a zoom or pan costs);
* ``drive_ms``: opening a drive (its detail, then its first matrix, fetched and drawn);
* ``overview_bytes``, ``drive_bytes``, ``matrix_bytes``, ``trace_bytes``,
  ``trace_page_bytes``: the JSON payloads (uncompressed) of the overview, a drive's detail, a
  matrix, the trace's timeline and a page of 200 trace frames.

The same is measured in the same run on a map of ``--baseline`` vertices (same city, fewer
drives); the table gives the large map's figures and their ratio to the baseline's::

    python tools/bench_viewer.py --vertices 1000000 --json viewer.json
    python tools/bench_viewer.py --vertices 20000 --baseline 5000 --runs 2     # smoke run

Maps are built under ``--workdir`` (default: a temporary directory, removed afterwards) and
kept there between runs when given (``--reuse``).
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from sprint_map.config import MapConfig
from sprint_map.localize.trace import TraceRecorder
from sprint_map.map import SprintMap
from sprint_map.storage.records import EdgeSpec
from tests.helpers.browser import ViewProcess, chromium, console_errors, wait_for

DIM = 16
TRACE_FRAMES = 300


class City:
    """Streets with smooth appearance and a position every 2 m along a wandering curve."""

    def __init__(self, n_streets: int, street_len: int, seed: int) -> None:
        rng = np.random.default_rng(seed)
        self.street_len = street_len
        raw = rng.standard_normal((n_streets * street_len + 4, DIM), dtype=np.float32)
        csum = np.cumsum(raw, axis=0, dtype=np.float64)
        self.appearance = ((csum[4:] - csum[:-4]) / 4).astype(np.float32)
        side = 2000.0 * np.sqrt(n_streets)  # metres
        xy = []
        for _ in range(n_streets):
            start = rng.uniform(0, side, 2)
            heading = rng.uniform(0, 2 * np.pi) + np.cumsum(rng.normal(0, 0.01, street_len))
            xy.append(start + np.cumsum(2.0 * np.c_[np.cos(heading), np.sin(heading)], axis=0))
        self.xy = np.vstack(xy)

    def drive(self, rng: np.random.Generator, street: int, frames: int
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(descriptors, positions, place of each frame)`` of one street's traversal."""
        pos = np.minimum(np.cumsum(rng.uniform(0.9, 1.1, frames)).astype(int),
                         self.street_len - 1)
        place = street * self.street_len + pos
        desc = self.appearance[place] + rng.normal(0, 0.3, (frames, DIM)).astype(np.float32)
        return desc.astype(np.float32), self.xy[place] + rng.normal(0, 1.0, (frames, 2)), place


def build(path: Path, n_vertices: int, args: argparse.Namespace) -> dict[str, Any]:
    n_drives = max(1, n_vertices // args.seq_len)
    n_streets = max(1, n_drives // args.revisits)
    city = City(n_streets, int(args.seq_len * 1.2), args.seed)
    rng = np.random.default_rng(args.seed + 1)
    last: dict[int, tuple[int, np.ndarray]] = {}  # street -> (seq id, place of each frame)
    start = time.perf_counter()
    with SprintMap.create(path, MapConfig(dim=DIM)) as m:
        for d in range(n_drives):
            street = d % n_streets
            desc, xy, place = city.drive(rng, street, args.seq_len)
            edges = []
            if street in last:
                old_seq, old_place = last[street]
                for i in range(0, args.seq_len, args.edge_every):
                    j = int(np.searchsorted(old_place, place[i]))
                    if j < len(old_place):
                        edges.append(EdgeSpec((None, i), (old_seq, j), 0.95, i))
                        edges.append(EdgeSpec((old_seq, j), (None, i), 0.95, i))
            added = m.add_sequence(desc, name=f"drive-{d:05d}", positions=xy, edges=edges)
            last[street] = (added.sequence.seq_id, place)
        stats = m.stats()
        # a trace: a new drive of street 0 localised against the map
        desc, _, _ = city.drive(rng, 0, TRACE_FRAMES)
        loc = m.localizer()
        rec = TraceRecorder(m)
        rec.attach(loc)
        loc.localize(desc)
        rec.save(path.parent / f"{path.name}.trace.npz")
    return {**stats, "build_s": round(time.perf_counter() - start, 1)}


def measure(path: Path, args: argparse.Namespace) -> dict[str, Any]:
    trace = path.parent / f"{path.name}.trace.npz"
    with ViewProcess(path, trace, path.parent / f"{path.name}.view.log") as view:
        out: dict[str, Any] = {"summarise_s": round(view.start_s, 2)}
        with httpx.Client(base_url=view.url, timeout=600) as client:
            ov = client.get("/viewer/api/overview")
            seq = ov.json()["sequences"]["id"][len(ov.json()["sequences"]["id"]) // 2]
            detail = client.get(f"/viewer/api/sequences/{seq}")
            other = detail.json()["matched"][0]["seq_id"]
            out |= {
                "overview_bytes": len(ov.content),
                "drive_bytes": len(detail.content),
                "matrix_bytes": len(client.get(f"/viewer/api/matrix/{seq}/{other}").content),
                "trace_bytes": len(client.get("/viewer/api/trace").content),
                "trace_page_bytes": len(client.get(
                    "/viewer/api/trace/frames?start=0&count=200").content),
            }
        runs: dict[str, list[float]] = {k: [] for k in (
            "first_paint_ms", "first_contentful_paint_ms", "overview_drawn_ms", "redraw_ms",
            "drive_ms")}
        with chromium() as driver:
            for _ in range(args.runs):
                driver.get("about:blank")
                driver.get(view.url)
                wait_for(driver, "window.sprintViewer && window.sprintViewer.ready", 600)
                paints = {e["name"]: e["startTime"] for e in driver.execute_script(
                    "return performance.getEntriesByType('paint').map(e => e.toJSON())")}
                runs["first_paint_ms"].append(paints.get("first-paint", float("nan")))
                runs["first_contentful_paint_ms"].append(
                    paints.get("first-contentful-paint", float("nan")))
                runs["overview_drawn_ms"].append(driver.execute_script(
                    "return window.sprintViewer.overviewDrawnAt"))
                runs["redraw_ms"].append(driver.execute_script(
                    "const t = performance.now(); window.sprintViewer.showTab('overview');"
                    "return performance.now() - t;"))
                drawn = driver.execute_script("return window.sprintViewer.drawn.length")
                assert drawn == len(ov.json()["sequences"]["id"]), drawn
                runs["drive_ms"].append(driver.execute_async_script(
                    "const done = arguments[arguments.length - 1], t = performance.now();"
                    f"window.sprintViewer.openDrive({seq}).then(() => done(performance.now() - t));"))
            errors = console_errors(driver)
        if errors:
            raise SystemExit(f"console errors: {errors}")
    return out | {k: round(statistics.median(v), 1) for k, v in runs.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--vertices", type=int, default=1_000_000)
    ap.add_argument("--baseline", type=int, default=10_000, help="vertices of the baseline map")
    ap.add_argument("--seq-len", type=int, default=2000)
    ap.add_argument("--revisits", type=int, default=5, help="drives per street")
    ap.add_argument("--edge-every", type=int, default=4)
    ap.add_argument("--runs", type=int, default=5, help="page loads (medians reported)")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--workdir", type=Path)
    ap.add_argument("--reuse", action="store_true", help="keep and reuse maps in --workdir")
    ap.add_argument("--json", type=Path, help="write the rows here")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        work = args.workdir or Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        rows = []
        for n in (args.baseline, args.vertices):
            path = work / f"viewer-{n}.map"
            built: dict[str, Any] = {}
            if not (args.reuse and path.exists()):
                if path.exists():
                    raise SystemExit(f"{path} exists (use --reuse, or another --workdir)")
                built = build(path, n, args)
            with SprintMap.open(path, readonly=True) as m:
                built = {**built, **m.stats()}
            rows.append({**built, **measure(path, args)})
    base, big = rows
    keys = [k for k in big if k not in ("sequences", "components")]
    print(f"{'measure':<28}{'baseline':>14}{'large':>14}{'ratio':>8}")
    for k in keys:
        ratio = big[k] / base[k] if isinstance(base.get(k), (int, float)) and base[k] else None
        print(f"{k:<28}{base.get(k, ''):>14}{big[k]:>14}"
              + (f"{ratio:>8.2f}" if ratio is not None else ""))
    if args.json:
        args.json.write_text(json.dumps({"rows": rows, "runs": args.runs}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
