"""Evaluation protocols end to end on a small frame-aligned data set of descriptor traversals."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli import main
from sprint_map.config import MapConfig
from sprint_map.evaluation.report import write_report
from sprint_map.evaluation.runner import EvalOptions, run_evaluation
from sprint_map.frontend.dataset import Dataset

DIM, FRAMES = 32, 150


@pytest.fixture
def dataset(tmp_path, rng):
    """Three frame-aligned traversals of one smooth route under different conditions."""
    cur = rng.standard_normal(DIM)
    places = []
    for _ in range(FRAMES):
        cur = 0.93 * cur + 0.37 * rng.standard_normal(DIM)
        places.append(cur / np.linalg.norm(cur))
    base = np.array(places)
    root = tmp_path / "data"
    for name in ("a-summer", "b-autumn", "c-winter"):
        x = base + 0.9 * rng.standard_normal(base.shape) / np.sqrt(DIM) * 4
        (root / name).mkdir(parents=True)
        np.save(root / name / "descriptors.npy",
                (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32))
    (root / "dataset.json").write_text(json.dumps({"alignment": "frame", "tolerance_frames": 1}))
    return root


@pytest.mark.parametrize("protocol", ["lifelong", "pairs"])
def test_protocols_score_knn_and_sprint(tmp_path, dataset, protocol):
    options = EvalOptions(protocol=protocol, both_directions=True)
    results = run_evaluation(Dataset.open(dataset), tmp_path / "maps", MapConfig(dim=DIM), options)
    queries = results["queries"]
    assert [q["query"] for q in queries] == (
        ["b-autumn", "c-winter"] if protocol == "lifelong" else ["b-autumn", "a-summer"])
    for q in queries:
        assert q["frames"] == q["frames_with_match"] == FRAMES
        assert q["knn_recall@1"] <= q["knn_recall@5"] <= q["knn_recall@10"]
        assert q["sprint_recall@1"] > q["knn_recall@1"]
        assert 0 <= q["pr_auc"] <= 1 and q["hmm_ms"]["p50"] > 0
    if protocol == "lifelong":
        assert queries[1]["map_vertices"] == 2 * FRAMES  # localised against both earlier drives
        assert queries[0]["edges_added"] > 0
    paths = write_report(results, tmp_path / "out")
    for path in paths.values():
        assert path.stat().st_size > 0
    saved = json.loads(paths["json"].read_text())
    assert saved["overall"]["frames"] == len(queries) * FRAMES
    assert "| query |" in paths["markdown"].read_text()


def test_eval_command_prints_the_table(tmp_path, dataset):
    result = CliRunner().invoke(main, ["eval", str(dataset), "--protocol", "pairs",
                                       "--out", str(tmp_path / "ev"), "-q"])
    assert result.exit_code == 0, result.output
    assert "SPRINT@1" in result.output and (tmp_path / "ev" / "pr_curve.png").is_file()
