"""The viewer in a real browser: ``sprint-map view`` on loopback, Debian's Chromium driven by
Selenium. Every drive of a generated map is drawn, a drive's matrix and a trace open, the
console stays free of errors; screenshots go to the test's tmp directory."""

from __future__ import annotations

import base64
import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sprint_map.config import MapConfig
from sprint_map.localize.trace import TraceRecorder
from sprint_map.map import SprintMap
from sprint_map.storage.records import EdgeSpec
from tests.helpers.browser import (
    ViewProcess,
    chromium,
    chromium_available,
    console_errors,
    wait_for,
)
from tests.helpers.road_map import DIM, build_road_map

pytestmark = [
    pytest.mark.browser,
    # .ci/run installs them and sets SPRINT_MAP_REQUIRE_BROWSER: there, never skipped
    pytest.mark.skipif(not chromium_available() and not os.environ.get("SPRINT_MAP_REQUIRE_BROWSER"),
                       reason="needs chromium, chromium-driver and selenium (.ci/run installs "
                              "them)"),
]

TOP_N = 6


@pytest.fixture(scope="module")
def shown(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """A map of five drives (two components) and a trace, served by ``sprint-map view``,
    and a browser on it."""
    tmp = tmp_path_factory.mktemp("viewer")
    rng = np.random.default_rng(20200531)
    road, ids = build_road_map(tmp / "m", rng, drives=4, frames=150, with_thumbnails=True)
    query, _ = road.drive(rng, 90, start=12)
    with SprintMap.open(tmp / "m", readonly=True) as m:
        loc = m.localizer()
        rec = TraceRecorder(m, top_n=TOP_N)
        rec.attach(loc)
        loc.localize(query)
        rec.save(tmp / "t.npz")
    with ViewProcess(tmp / "m", tmp / "t.npz", tmp / "view.log") as view, chromium() as driver:
        driver.get(view.url)
        wait_for(driver, "window.sprintViewer && window.sprintViewer.ready")
        yield driver, ids, tmp


def pixels_near(driver: Any, canvas: str, x: float, y: float, r: int = 3) -> np.ndarray:
    """The canvas's RGB pixels in a (2r+1)^2 square around CSS point (x, y)."""
    data = driver.execute_script(
        """const c = document.getElementById(arguments[0]);
           const k = c.width / c.clientWidth, r = arguments[3];
           const d = c.getContext('2d').getImageData(Math.round(arguments[1] * k) - r,
               Math.round(arguments[2] * k) - r, 2 * r + 1, 2 * r + 1).data;
           return Array.from(d);""", canvas, x, y, r)
    return np.array(data, np.int64).reshape(-1, 4)[:, :3]


def shoot(driver: Any, path: Path) -> None:
    driver.save_screenshot(str(path))
    assert path.stat().st_size > 10_000


def test_every_drive_is_drawn_in_its_components_colour(shown):
    driver, ids, tmp = shown
    assert sorted(driver.execute_script("return window.sprintViewer.drawn")) == sorted(ids)
    for seq in ids:
        x, y = driver.execute_script("return window.sprintViewer.screenOf(arguments[0])", seq)
        colour = np.array(driver.execute_script(
            "return window.sprintViewer.colourOf(arguments[0])", seq))
        near = pixels_near(driver, "overview-canvas", x, y)
        assert (np.abs(near - colour).sum(axis=1) < 30).any(), (seq, colour, near[:5])
    # two components, two colours; the list has a row per drive
    colours = {tuple(driver.execute_script("return window.sprintViewer.colourOf(arguments[0])", s))
               for s in ids}
    assert len(colours) == 2
    rows = driver.find_elements("css selector", "#drive-list tbody tr")
    assert len(rows) == len(ids)
    assert "5 drives" in driver.find_element("id", "counts").text
    shoot(driver, tmp / "overview.png")
    assert console_errors(driver) == []


def test_a_drive_opens_with_its_matrix_and_decisions(shown):
    driver, ids, tmp = shown
    driver.find_element("id", f"drive-row-{ids[1]}").click()
    wait_for(driver, f"window.sprintViewer.driveShown === {ids[1]}")
    assert driver.execute_script("return window.sprintViewer.matrixShown") in (ids[0], ids[2])
    buttons = driver.find_elements("css selector", "#matched button")
    assert len(buttons) == 2  # the drives before and after it on the road
    png = driver.find_element("id", "matrix-canvas").screenshot_as_base64
    from io import BytesIO

    from matplotlib.image import imread

    img = imread(BytesIO(base64.b64decode(png)))[..., :3]
    red = (img[..., 0] > 0.8) & (img[..., 1] < 0.35) & (img[..., 2] < 0.35)
    assert red.sum() > 50  # the decisions drawn as a path
    grey = np.abs(img[..., 0] - img[..., 2]) < 0.02
    assert img[grey].std() > 0.1  # a matrix, not a blank canvas
    assert "precision" in driver.find_element("id", "pr").text
    buttons[1].click()
    other = int(buttons[1].get_attribute("data-other"))
    wait_for(driver, f"window.sprintViewer.matrixShown === {other}")
    # the map keeps thumbnails: the frames under the pointer are shown
    from selenium.webdriver import ActionChains

    ActionChains(driver).move_to_element_with_offset(
        driver.find_element("id", "matrix-canvas"), 10, 20).perform()
    wait_for(driver, "document.getElementById('thumb-b').naturalWidth > 0", 30)
    assert driver.execute_script("return document.getElementById('thumb-a').naturalWidth") == 64
    assert f"sequence {other}" in driver.find_element("id", "thumb-b-cap").text
    shoot(driver, tmp / "drive.png")
    assert console_errors(driver) == []


def test_a_trace_plays_back_frame_by_frame(shown):
    driver, _, tmp = shown
    driver.find_element("css selector", 'nav .tab[data-tab="trace"]').click()
    wait_for(driver, "window.sprintViewer.traceFrame === 0")
    driver.find_element("id", "play").click()
    wait_for(driver, "window.sprintViewer.traceFrame >= 5")
    driver.find_element("id", "play").click()  # pause
    frame = driver.execute_script("return window.sprintViewer.traceFrame")
    label = driver.find_element("id", "frame-label").text
    assert label.startswith(f"frame {frame} / 89")
    rows = driver.find_elements("css selector", "#top-states tbody tr")
    assert len(rows) == TOP_N
    detail = driver.find_element("id", "frame-detail").text
    assert "Decision:" in detail and "Active set:" in detail
    shoot(driver, tmp / "trace.png")
    assert console_errors(driver) == []


def test_a_map_without_positions_is_drawn_as_a_graph(tmp_path, rng):
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        for i in range(5):
            edges = [EdgeSpec((None, 0), (i - 1, 0), 1.0)] if i in (1, 2, 4) else []
            m.add_sequence(rng.standard_normal((20, DIM)).astype(np.float32), edges=edges)
    with ViewProcess(tmp_path / "m") as view, chromium() as driver:
        driver.get(view.url)
        wait_for(driver, "window.sprintViewer && window.sprintViewer.ready")
        assert sorted(driver.execute_script("return window.sprintViewer.drawn")) == list(range(5))
        for seq in range(5):
            x, y = driver.execute_script("return window.sprintViewer.screenOf(arguments[0])", seq)
            colour = driver.execute_script("return window.sprintViewer.colourOf(arguments[0])", seq)
            assert (np.abs(pixels_near(driver, "overview-canvas", x, y) - colour).sum(1) < 30).any()
        # the trace tab stays hidden without a trace, and nothing failed
        assert not driver.find_element("css selector", 'nav .tab[data-tab="trace"]').is_displayed()
        assert console_errors(driver) == []


def test_with_a_token_the_page_asks_for_it(tmp_path, rng):
    build_road_map(tmp_path / "m", rng, drives=2, frames=40)
    with ViewProcess(tmp_path / "m", env={"SPRINT_MAP_TOKEN": "s3cret"}) as view, \
            chromium() as driver:
        driver.get(view.url)
        wait_for(driver, "!document.getElementById('login').hidden")
        assert not driver.execute_script("return window.sprintViewer.ready")
        driver.find_element("id", "token").send_keys("s3cret")
        driver.find_element("css selector", "#login button").click()
        wait_for(driver, "window.sprintViewer.ready")
        assert len(driver.execute_script("return window.sprintViewer.drawn")) == 3
        # the 401 answers before the token are the only console errors
        assert all("401" in e for e in console_errors(driver))
