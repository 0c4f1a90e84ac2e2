"""``sprint-map view``: what it refuses before serving, and a real process's announcement."""

from __future__ import annotations

import httpx
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from tests.helpers.browser import ViewProcess

pytestmark = pytest.mark.road_map(drives=2, frames=40)


def test_help_has_an_example():
    out = CliRunner().invoke(main, ["view", "--help"])
    assert out.exit_code == 0 and "sprint-map view city.map --trace" in out.output


@pytest.mark.parametrize("args, message", [
    (["--trace", "{tmp}/missing.npz"], "not a sprint-map trace"),
    (["--host", "0.0.0.0"], "without a bearer token"),
])
def test_refused_before_serving(road_map, tmp_path, monkeypatch, args, message):
    monkeypatch.delenv("SPRINT_MAP_TOKEN", raising=False)
    args = [a.format(tmp=tmp_path) for a in args]
    out = CliRunner().invoke(main, ["view", str(road_map.path), *args])
    assert out.exit_code != 0 and message in out.output
    assert out.output.startswith("Error: ") and "Traceback" not in out.output


def test_a_view_process_serves_the_map_read_only_and_stops_on_sigterm(road_map, tmp_path):
    with ViewProcess(road_map.path, log=tmp_path / "log") as view:
        ov = httpx.get(view.url + "/viewer/api/overview", timeout=30).json()
        assert ov["counts"]["sequences"] == 3 and ov["trace"] is False
        # read-only: another process can still write the map meanwhile
        out = CliRunner().invoke(main, ["remove", str(road_map.path), "drive-0"])
        assert out.exit_code == 0, out.output
        again = httpx.get(view.url + "/viewer/api/overview", timeout=30).json()
        assert again["counts"]["sequences"] == 2
    assert view.proc.returncode == 0
