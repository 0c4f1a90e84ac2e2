"""Screenshots of the viewer for the docs: a small generated town, its drives merged, a trace.

The town has four streets; six drives follow routes over them (each street seen under its own
appearance change by each drive), one more drives streets nobody else did. The drives are
ingested (localised, then merged), a seventh is localised with a trace, ``sprint-map view``
serves the map and Debian's Chromium (Selenium, ``tests.helpers.browser``) takes::

    docs/viewer-overview.png   the overview
    docs/viewer-drive.png      a drive against one it matched (tue against mon)
    docs/viewer-trace.png      the trace's playback

    python tools/viewer_screenshots.py --out docs
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from sprint_map.config import MapConfig
from sprint_map.localize.trace import TraceRecorder
from sprint_map.map import SprintMap
from tests.helpers.browser import ViewProcess, chromium, console_errors, wait_for

DIM = 64


def unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def streets(rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """Four streets: ``(appearance, xy)`` of a place every 4 m."""
    shapes = [
        lambda t: np.c_[t, 40 * np.sin(t / 150)],                      # east-west, wavy
        lambda t: np.c_[600 + 30 * np.sin(t / 90), t],                  # north-south
        lambda t: np.c_[600 - t, 600 + 0.2 * t],                        # back west
        lambda t: np.c_[t * 0.7, 600 - t * 0.7 + 40 * np.cos(t / 60)],  # diagonal
    ]
    out = []
    for shape in shapes:
        t = np.arange(0, 600, 4.0)
        cur, app = unit(rng.standard_normal(DIM)), []
        for _ in t:
            cur = unit(0.9 * cur + np.sqrt(1 - 0.81) * unit(rng.standard_normal(DIM)))
            app.append(cur)
        out.append((np.array(app), shape(t)))
    return out


def drive(rng: np.random.Generator, town: list[tuple[np.ndarray, np.ndarray]],
          route: list[int]) -> tuple[np.ndarray, np.ndarray]:
    descs, xys = [], []
    shift = unit(rng.standard_normal(DIM)) * 0.3
    for s in route:
        app, xy = town[s]
        pos = np.cumsum(rng.uniform(0.8, 1.2, int(len(app) * 0.95))) - 1
        idx = np.clip(pos.astype(int), 0, len(app) - 1)
        descs.append(unit(app[idx] + shift + 0.6 * unit(rng.standard_normal((len(idx), DIM)))))
        xys.append(xy[idx] + rng.normal(0, 1.0, (len(idx), 2)))
    return np.vstack(descs), np.vstack(xys)


def build(path: Path, trace: Path, seed: int) -> None:
    rng = np.random.default_rng(seed)
    town = streets(rng)
    other = streets(np.random.default_rng(seed + 1))
    other = [(a, xy + [900, 0]) for a, xy in other]  # another town, never matched
    routes = [("mon", town, [0, 1]), ("tue", town, [0, 1, 2]), ("wed", town, [3]),
              ("thu", town, [1, 2]), ("fri", town, [3, 0]), ("sat", town, [2]),
              ("far", other, [0, 1])]
    with SprintMap.create(path, MapConfig(dim=DIM)) as m:
        for name, where, route in routes:
            desc, xy = drive(rng, where, route)
            m.ingest(desc, name=name, positions=xy)
        desc, _ = drive(rng, town, [0, 1])
        rec = TraceRecorder(m)
        final, _ = m.localize(desc, smooth=True, observe=rec.attach)
        rec.save(trace, final=final, meta={"command": "localize", "smoothed": True,
                                                    "source": "sun.npy"})


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("docs"))
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path, trace = Path(tmp) / "town.map", Path(tmp) / "sun.npz"
        build(path, trace, args.seed)
        with ViewProcess(path, trace) as view, chromium(1280, 820) as driver:
            driver.get(view.url)
            wait_for(driver, "window.sprintViewer && window.sprintViewer.ready")
            driver.save_screenshot(str(args.out / "viewer-overview.png"))
            driver.find_element("id", "drive-row-1").click()  # tue
            wait_for(driver, "window.sprintViewer.matrixShown !== undefined")
            # against mon, the drive before it: tue's own decisions (its merge edges)
            driver.find_element("css selector", '#matched button[data-other="0"]').click()
            wait_for(driver, "window.sprintViewer.matrixShown === 0")
            time.sleep(0.3)
            driver.save_screenshot(str(args.out / "viewer-drive.png"))
            driver.find_element("css selector", 'nav .tab[data-tab="trace"]').click()
            driver.execute_script("window.sprintViewer.setFrame(120)")
            wait_for(driver, "window.sprintViewer.traceFrame === 120")
            driver.save_screenshot(str(args.out / "viewer-trace.png"))
            errors = console_errors(driver)
    if errors:
        raise SystemExit(f"console errors: {errors}")
    print("\n".join(str(args.out / f"viewer-{n}.png") for n in ("overview", "drive", "trace")))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
