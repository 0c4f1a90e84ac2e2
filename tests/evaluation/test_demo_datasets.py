"""The demo's generated worlds: ``city-novel`` renders its own preset and runs the lifelong
evaluation; ``latent`` generates the descriptor-level world and evaluates it the same way; an
unknown choice is refused."""

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


#: Keys every query row and the overall row of results.json have, whatever the world.
ROW_KEYS = {"query", "frames", "frames_with_match", "knn_recall@1", "knn_recall@10",
            "sprint_recall@1", "smoothed_recall@1", "merge_precision", "merge_recall",
            "merged_decisions", "edges_added", "edges_wrong", "novel_merged",
            "no_match_on_novel", "decision_precision"}


def test_latent_demo_generates_the_world_and_evaluates(tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(demo, "LATENT_TRAVERSALS", 4)
    monkeypatch.setattr(demo, "LATENT_FRAMES", 120)
    results, paths = demo.run_demo(tmp_path, "latent")
    info = json.loads((tmp_path / "latent" / "dataset.json").read_text())
    assert info["generator"]["module"] == "sprint_map.synth.latent"
    assert info["generator"]["config"]["novel_fraction"] == 0.5
    assert not (tmp_path / "city").exists()
    assert results["protocol"] == "lifelong"
    assert results["config"]["descriptor"] == "precomputed" and results["config"]["dim"] == 256
    assert [q["query"] for q in results["queries"]] == ["t01-overcast", "t02-dusk", "t03-rain"]
    for row in [*results["queries"], results["overall"]]:
        assert set(row) >= ROW_KEYS
        # The world declares its identical twins: evaluation counts their frames apart.
        assert 0 <= row["twin_merged_wrong"] <= row["twin_merged"] <= row["twin_frames"]
    assert results["overall"]["frames_with_match"] > 0
    assert results["overall"]["twin_frames"] == sum(q["twin_frames"] for q in results["queries"])
    assert paths["json"] == tmp_path / "results.json" and paths["json"].is_file()


@pytest.mark.slow
def test_latent_demo_at_full_size_is_as_hard_as_the_issue_says(tmp_path: Path) -> None:
    """``sprint-map demo --dataset latent`` as shipped (10 x 300 frames, ~40 s): exact k-NN@1
    30-45 % and k-NN@10 65-85 % over the frames with a true match."""
    from click.testing import CliRunner

    from sprint_map.cli.main import main

    result = CliRunner().invoke(main, ["demo", "--dataset", "latent", "--out",
                                       str(tmp_path / "out"), "-q"])
    assert result.exit_code == 0, result.output
    overall = json.loads((tmp_path / "out" / "results.json").read_text())["overall"]
    assert overall["frames"] == 9 * 300
    assert 0.30 <= overall["knn_recall@1"] <= 0.45 and 0.65 <= overall["knn_recall@10"] <= 0.85
    assert overall["twin_frames"] > 0


def test_unknown_demo_dataset_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="city-novel"):
        demo.run_demo(tmp_path, "mars")
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("which", ["city", "city-novel", "latent"])
def test_cli_demo_dataset_writes_results_in_sprint_demo(which: str, tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """``sprint-map demo --dataset city|city-novel|latent``: ./sprint-demo/results.json by
    default."""
    from click.testing import CliRunner

    from sprint_map.cli.main import main

    monkeypatch.setattr(demo, "CITY_TRAVERSALS", 2)
    monkeypatch.setattr(demo, "CITY_FRAMES", 30)
    monkeypatch.setattr(demo, "LATENT_TRAVERSALS", 2)
    monkeypatch.setattr(demo, "LATENT_FRAMES", 100)
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(main, ["demo", "--dataset", which, "-q"])
    assert result.exit_code == 0, result.output
    assert "SPRINT@1" in result.output
    results = json.loads((tmp_path / "sprint-demo" / "results.json").read_text())
    assert results["protocol"] == "lifelong" and len(results["queries"]) == 1
    assert (tmp_path / "sprint-demo" / which / "dataset.json").is_file()
