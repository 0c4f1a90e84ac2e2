"""eval/demo --gnss-sigma: the protocol again GNSS-aided, beside image only."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.config import MapConfig
from sprint_map.errors import InputError
from sprint_map.evaluation.report import markdown_table
from sprint_map.evaluation.runner import EvalOptions, run_evaluation
from sprint_map.frontend.dataset import Dataset
from sprint_map.map import SprintMap

DIM, FRAMES = 32, 150
MERGE_KEYS = ("merge_precision", "merge_recall", "merged_decisions", "edges_added",
              "edges_wrong", "novel_merged", "smoothed_recall@1", "sprint_recall@1")


@pytest.fixture
def placed(tmp_path):
    """Three traversals of one straight street (5 m between frames, positions.csv with
    heading), each seen with fresh noise."""
    rng = np.random.default_rng(0)
    cur = rng.standard_normal(DIM)
    places = []
    for _ in range(FRAMES):
        cur = 0.93 * cur + 0.37 * rng.standard_normal(DIM)
        places.append(cur / np.linalg.norm(cur))
    base = np.array(places)
    root = tmp_path / "placed"
    for name in ("a-day", "b-dusk", "c-night"):
        x = base + 1.8 * rng.standard_normal(base.shape) / np.sqrt(DIM)
        (root / name).mkdir(parents=True)
        np.save(root / name / "descriptors.npy",
                (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32))
        (root / name / "positions.csv").write_text(
            "frame,x,y,heading_deg\n" + "".join(f"{i},{i * 5.0},0,0\n" for i in range(FRAMES)))
    (root / "dataset.json").write_text(json.dumps({"alignment": "position", "radius_m": 8.0}))
    return root


def test_lifelong_reports_the_aided_run_beside_image_only(tmp_path, placed):
    data = Dataset.open(placed)
    config = MapConfig(dim=DIM)
    plain = run_evaluation(data, tmp_path / "plain", config, EvalOptions())
    both = run_evaluation(data, tmp_path / "both", config, EvalOptions(gnss_sigma=10.0))
    assert "gnss" not in plain
    # the image-only rows are those of a run without GNSS
    for a, b in zip(plain["queries"], both["queries"], strict=True):
        assert {k: a[k] for k in MERGE_KEYS} == {k: b[k] for k in MERGE_KEYS}
    gnss = both["gnss"]
    assert gnss["sigma_m"] == 10.0 and gnss["seed"] == 0 and gnss["model"]["sigma"] == 10.0
    assert [q["query"] for q in gnss["queries"]] == ["b-dusk", "c-night"]
    for row in [*gnss["queries"], gnss["overall"]]:
        assert set(MERGE_KEYS) <= set(row)
    assert gnss["overall"]["merged_decisions"] > 0
    # the aided maps store the simulated fixes (a dropout: no position), not ground truth
    with SprintMap.open(tmp_path / "both" / "map-lifelong-gnss", readonly=True) as m:
        pos = m.positions(m.sequence_by_name("a-day").seq_id)
    assert pos is not None
    truth = np.c_[np.arange(FRAMES) * 5.0, np.zeros(FRAMES)]
    err = np.hypot(*(pos[:, :2] - truth).T)
    assert 0 < np.nanmedian(err) < 40
    assert "GNSS-aided beside image only" in markdown_table(both)


def test_pairs_reports_the_aided_run(tmp_path, placed):
    out = run_evaluation(Dataset.open(placed), tmp_path / "pairs", MapConfig(dim=DIM),
                         EvalOptions(protocol="pairs", gnss_sigma=5.0))
    assert len(out["gnss"]["queries"]) == 1 and "merge_precision" in out["gnss"]["overall"]


def test_a_traversal_without_positions_cannot_be_aided(tmp_path, placed):
    (placed / "b-dusk" / "positions.csv").unlink()
    (placed / "dataset.json").write_text(json.dumps({"alignment": "frame"}))
    with pytest.raises(InputError, match="b-dusk.*--gnss-sigma simulates fixes from positions"):
        run_evaluation(Dataset.open(placed), tmp_path / "x", MapConfig(dim=DIM),
                       EvalOptions(gnss_sigma=10.0))


@pytest.mark.parametrize("sigma", [-1.0, float("nan"), float("inf")])
def test_a_bad_sigma_is_one_error_line(tmp_path, placed, sigma):
    result = CliRunner().invoke(main, ["eval", str(placed), "--out", str(tmp_path / "o"),
                                       "--gnss-sigma", str(sigma), "--quiet"])
    assert result.exit_code == InputError.exit_code
    assert result.output.strip().splitlines() == [
        f"Error: --gnss-sigma must be a finite number >= 0 metres (0: off), got {sigma}"]
    assert not (tmp_path / "o").exists()


def test_eval_command_writes_the_gnss_object(tmp_path, placed):
    out = tmp_path / "out"
    result = CliRunner().invoke(main, ["eval", str(placed), "--out", str(out),
                                       "--gnss-sigma", "10", "--quiet"])
    assert result.exit_code == 0, result.output
    saved = json.loads((out / "results.json").read_text())
    assert saved["gnss"]["sigma_m"] == 10.0
    assert saved["gnss"]["overall"]["merge_precision"] == pytest.approx(
        saved["gnss"]["overall"]["merge_precision"])
    assert "GNSS-aided" in result.output
