"""tools/bench_merge_rule.py: config overrides, a cached world, a tiny run with a baseline."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from sprint_map import MapConfig
from sprint_map.errors import ConfigError
from tools import bench_merge_rule as bench


def test_overrides_go_to_the_map_or_the_hmm_config() -> None:
    changes = bench.parse_overrides(["merge_max_contrast=0.9", "merge.min_run=12", "k=14",
                                      "hmm.window=[0.5, 0.5]", "store.index_type=flat"])
    assert changes == {"merge_max_contrast": 0.9, "merge": {"min_run": 12},
                       "hmm": {"k": 14, "window": [0.5, 0.5]}, "store": {"index_type": "flat"}}
    config = bench.configured(MapConfig(dim=8), changes)
    assert (config.merge.max_contrast, config.merge.min_run, config.hmm.k) == (0.9, 12, 14)
    assert config.store.index_type == "flat"
    assert config.hmm.window == (0.5, 0.5)
    assert config.dim == 8


@pytest.mark.parametrize("pairs", [["merge_max_contrast"], ["no_such_field=1"], ["hmm.dim=3"]])
def test_bad_overrides_are_refused(pairs: list[str]) -> None:
    with pytest.raises(ConfigError):
        bench.parse_overrides(pairs)


def test_bad_override_value_stops_before_any_work(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        bench.main(["--family", "latent", "--cache", str(tmp_path), "--set", "k=1.5"])
    assert "k" in capsys.readouterr().err and not any(tmp_path.iterdir())


def test_tiny_latent_run_with_baseline(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                       ) -> None:
    out = tmp_path / "m.json"
    args = ["--family", "latent", "--seeds", "0", "--traversals", "3", "--frames", "120",
            "--cache", str(tmp_path / "cache"), "--set", "merge_min_run=10", "--json", str(out)]
    assert bench.main(args) == 0
    data = json.loads(out.read_text())
    runs = data["families"]["latent"]["runs"]
    assert [r["arm"] for r in runs] == ["default", "tuned"]
    default, tuned = (r["results"] for r in runs)
    assert default["merge_rule"]["merge_min_run"] != tuned["merge_rule"]["merge_min_run"] == 10
    figures = runs[0]["figures"]
    overall = default["overall"]
    assert figures["merge_precision"] == overall["merge_precision"]
    assert figures["twin_frames"] == overall["twin_frames"]
    assert set(data["families"]["latent"]["mean"]) == {"default", "tuned"}
    printed = capsys.readouterr().out
    assert "mergeP" in printed and "latent (3 x 120 frames per seed)" in printed
    # The world is cached: a second run generates nothing.
    [world] = (tmp_path / "cache").iterdir()
    stamp = (world / "dataset.json").stat().st_mtime_ns
    assert bench.main(args[:-4] + ["--no-baseline", "--set", "merge_min_run=10"]) == 0
    assert (world / "dataset.json").stat().st_mtime_ns == stamp
