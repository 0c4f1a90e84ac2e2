"""The demo's generated worlds: ``city-novel`` renders its own preset and runs the lifelong
evaluation; an unknown choice is refused."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sprint_map.errors import ConfigError
from sprint_map.evaluation import demo


def test_city_novel_demo_renders_the_preset_and_evaluates(tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(demo, "CITY_TRAVERSALS", 3)
    monkeypatch.setattr(demo, "CITY_FRAMES", 40)
    results, paths = demo.run_demo(tmp_path, "city-novel")
    generator = json.loads((tmp_path / "city-novel" / "dataset.json").read_text())["generator"]
    assert generator["config"]["novel_fraction"] == 0.6
    assert generator["config"]["alias_streets"] == 0.25
    assert not (tmp_path / "city").exists()  # the plain city is not rendered
    assert results["protocol"] == "lifelong"
    assert [q["query"] for q in results["queries"]] == ["t01-overcast", "t02-dusk"]
    assert paths["json"] == tmp_path / "results.json" and paths["json"].is_file()


def test_unknown_demo_dataset_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="city-novel"):
        demo.run_demo(tmp_path, "mars")
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("which", ["city", "city-novel"])
def test_cli_demo_dataset_writes_results_in_sprint_demo(which: str, tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """``sprint-map demo --dataset city|city-novel``: ./sprint-demo/results.json by default."""
    from click.testing import CliRunner

    from sprint_map.cli.main import main

    monkeypatch.setattr(demo, "CITY_TRAVERSALS", 2)
    monkeypatch.setattr(demo, "CITY_FRAMES", 30)
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(main, ["demo", "--dataset", which, "-q"])
    assert result.exit_code == 0, result.output
    assert "SPRINT@1" in result.output
    results = json.loads((tmp_path / "sprint-demo" / "results.json").read_text())
    assert results["protocol"] == "lifelong" and len(results["queries"]) == 1
    assert (tmp_path / "sprint-demo" / which / "dataset.json").is_file()
