"""Evaluation protocols end to end on a small frame-aligned data set of descriptor traversals."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.config import MapConfig
from sprint_map.evaluation.metrics import merge_metrics
from sprint_map.evaluation.report import write_report
from sprint_map.evaluation.runner import EvalOptions, describe, run_evaluation
from sprint_map.frontend.dataset import Dataset
from sprint_map.map import SprintMap

DIM, FRAMES, DETOUR = 32, 150, 60
#: Per-frame noise: k-NN@1 errs often, yet the drives are matched well enough to be merged
#: (at 3.0 the smoothed decisions are mostly wrong and the merge rule, rightly, merges none).
NOISE = 2.0
#: What every query row and ``overall`` carry (the issue-13 contract, plus the smoothed recall).
CONTRACT = ("sprint_recall@1", "recall@100%precision", "smoothed_recall@1", "merge_precision",
            "merge_recall", "edges_added", "edges_wrong", "novel_merged")


def _route(rng, frames):
    cur = rng.standard_normal(DIM)
    places = []
    for _ in range(frames):
        cur = 0.93 * cur + 0.37 * rng.standard_normal(DIM)
        places.append(cur / np.linalg.norm(cur))
    return np.array(places)


def _write(root, rng, traversals):
    """Frame-aligned traversals: ``name -> (frames, dim)`` places, each seen with fresh noise."""
    for name, base in traversals.items():
        x = base + 0.9 * rng.standard_normal(base.shape) / np.sqrt(DIM) * NOISE
        (root / name).mkdir(parents=True)
        np.save(root / name / "descriptors.npy",
                (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32))
    (root / "dataset.json").write_text(json.dumps({"alignment": "frame", "tolerance_frames": 1}))
    return root


@pytest.fixture
def dataset(tmp_path, rng):
    """Three frame-aligned traversals of one smooth route under different conditions."""
    base = _route(rng, FRAMES)
    return _write(tmp_path / "data", rng, {n: base for n in ("a-summer", "b-autumn", "c-winter")})


@pytest.fixture
def detour_dataset(tmp_path, rng):
    """Two traversals of a route, then one that drives it and goes on into DETOUR frames of
    streets no earlier traversal saw (frame alignment: past the others' length, no match)."""
    base = _route(rng, FRAMES)
    longer = np.vstack([base, _route(rng, DETOUR)])
    return _write(tmp_path / "detour", rng,
                  {"a-summer": base, "b-autumn": base, "c-detour": longer})


def _check_rows(results):
    """The contract's keys, and the merge metrics consistent with each other."""
    both_ways = results["merge_rule"]["merge_both_ways"]
    for row in [*results["queries"], results["overall"]]:
        assert set(CONTRACT) <= set(row), row["query"]
        assert 0 <= row["merge_precision"] <= 1 and 0 <= row["merge_recall"] <= 1
        assert 0 <= row["novel_merged"] <= 1
        assert 0 <= row["edges_wrong"] <= row["edges_added"]
        assert row["edges_added"] == (2 if both_ways else 1) * row["merged_decisions"]
    queries, overall = results["queries"], results["overall"]
    for key in ("edges_added", "edges_wrong", "merged_decisions"):
        assert overall[key] == sum(q[key] for q in queries)


@pytest.mark.parametrize("protocol", ["lifelong", "pairs"])
def test_protocols_score_knn_and_sprint(tmp_path, dataset, protocol):
    options = EvalOptions(protocol=protocol, both_directions=True)
    config = MapConfig(dim=DIM)
    results = run_evaluation(Dataset.open(dataset), tmp_path / "maps", config, options)
    queries = results["queries"]
    assert [q["query"] for q in queries] == (
        ["b-autumn", "c-winter"] if protocol == "lifelong" else ["b-autumn", "a-summer"])
    for q in queries:
        assert q["frames"] == q["frames_with_match"] == FRAMES
        assert q["knn_recall@1"] <= q["knn_recall@5"] <= q["knn_recall@10"]
        assert q["sprint_recall@1"] > q["knn_recall@1"]
        assert q["smoothed_recall@1"] > q["knn_recall@1"]
        assert 0 <= q["pr_auc"] <= 1 and q["hmm_ms"]["p50"] > 0
        # every frame has a match here: nothing merged is novel
        assert q["merged_decisions"] > 0 and q["novel_merged"] == 0
    _check_rows(results)
    assert results["merge_rule"] == config.merge.reported()
    by_traversal = results["recall_by_traversal"]
    assert [r["query"] for r in by_traversal] == [q["query"] for q in queries]
    assert [r["sprint_recall@1"] for r in by_traversal] == [q["sprint_recall@1"] for q in queries]
    if protocol == "lifelong":
        assert [r["traversal"] for r in by_traversal] == [1, 2]
        assert queries[1]["map_vertices"] == 2 * FRAMES  # localised against both earlier drives
        assert queries[0]["edges_added"] > 0
        with SprintMap.open(tmp_path / "maps" / "map-lifelong", readonly=True) as m:
            assert len(m.edges()) == results["overall"]["edges_added"]  # what was committed
    paths = write_report(results, tmp_path / "out")
    assert ("recall_by_traversal" in paths) == (protocol == "lifelong")
    for path in paths.values():
        assert path.stat().st_size > 0
    saved = json.loads(paths["json"].read_text())
    assert saved["overall"]["frames"] == len(queries) * FRAMES
    assert saved["merge_rule"] == results["merge_rule"]
    table = paths["markdown"].read_text()
    assert "| query |" in table and "| merge P | merge R | edges (wrong) |" in table
    o = results["overall"]
    assert f"| {o['edges_added']} ({o['edges_wrong']}) |" in table
    assert f"threshold {config.merge.threshold}" in table


def test_lifelong_merge_metrics_match_the_edges_committed(tmp_path, detour_dataset):
    """The metrics of the detour drive, recomputed from the edges its ingest committed (their
    provenance) and the ground truth: the runner scores what the map holds."""
    data = Dataset.open(detour_dataset)
    results = run_evaluation(data, tmp_path / "maps", MapConfig(dim=DIM),
                             EvalOptions(protocol="lifelong"))
    _check_rows(results)
    row = results["queries"][-1]
    assert row["query"] == "c-detour"
    # frame FRAMES is within the tolerance (1 frame) of the last mapped one
    assert row["frames"] == FRAMES + DETOUR and row["frames_with_match"] == FRAMES + 1
    gt = data.ground_truth(1)
    with SprintMap.open(tmp_path / "maps" / "map-lifelong", readonly=True) as m:
        names = {s.seq_id: s.name for s in m.sequences()}
        seq = m.store.sequence_by_name("c-detour").seq_id
        forward = [e for e in m.edges(added_by="c-detour") if e.src_seq == seq]
        assert len(m.edges(added_by="c-detour")) == row["edges_added"] == 2 * len(forward)
    frames = np.arange(FRAMES + DETOUR)
    merged = np.zeros(len(frames), dtype=bool)
    correct = np.zeros(len(frames), dtype=bool)
    for e in forward:
        merged[e.src_image] = True
        correct[e.src_image] = bool(gt.correct("c-detour", e.src_image, names[e.dst_seq],
                                               e.dst_image))
    has_match = gt.has_match("c-detour", frames, ["a-summer", "b-autumn"])
    expect = merge_metrics(merged, correct, has_match, 2)
    assert row["merge_precision"] == pytest.approx(expect.precision, abs=1e-4)
    assert row["merge_recall"] == pytest.approx(expect.recall, abs=1e-4)
    assert row["novel_merged"] == pytest.approx(expect.novel_merged, abs=1e-4)
    assert row["edges_wrong"] == expect.edges_wrong


def test_pairs_scores_the_merge_that_would_be_made(tmp_path, detour_dataset):
    """pairs: the query is not merged; the metrics are the map's merge rule over the query's
    smoothed decisions (:meth:`SprintMap.localize` with ``smooth=True``), edges counted as if
    merged."""
    data = Dataset.open(detour_dataset)
    options = EvalOptions(protocol="pairs", database="a-summer", query="c-detour")
    results = run_evaluation(data, tmp_path / "maps", MapConfig(dim=DIM), options)
    _check_rows(results)
    (row,) = results["queries"]
    gt = data.ground_truth(1)
    with SprintMap.open(tmp_path / "maps" / "map-a-summer", readonly=True) as m:
        assert [s.name for s in m.sequences()] == ["a-summer"] and not m.edges()
        rows = describe(m, data["c-detour"], 1)
        decisions, _ = m.localize(rows, smooth=True)
        merged = m.service.select_merges(decisions)
        db = m.sequences()[0].seq_id
    correct = np.array([d.seq_id == db and d.image_id is not None
                        and bool(gt.correct("c-detour", d.frame, "a-summer", d.image_id))
                        for d in decisions])
    best = np.array([d.best is not None and bool(gt.correct("c-detour", d.frame, "a-summer",
                                                            d.best[1])) for d in decisions])
    has_match = gt.has_match("c-detour", np.arange(len(rows)), "a-summer")
    expect = merge_metrics(merged, correct, has_match, 2)
    assert merged.any() and (~has_match).any()
    assert row["edges_added"] == expect.edges_added and row["edges_wrong"] == expect.edges_wrong
    assert row["merge_precision"] == pytest.approx(expect.precision, abs=1e-4)
    assert row["merge_recall"] == pytest.approx(expect.recall, abs=1e-4)
    assert row["novel_merged"] == pytest.approx(expect.novel_merged, abs=1e-4)
    assert row["smoothed_recall@1"] == pytest.approx(
        (best & has_match).sum() / has_match.sum(), abs=1e-4)


def test_eval_command_prints_the_table(tmp_path, dataset):
    result = CliRunner().invoke(main, ["eval", str(dataset), "--protocol", "pairs",
                                       "--out", str(tmp_path / "ev"), "-q"])
    assert result.exit_code == 0, result.output
    assert "SPRINT@1" in result.output and (tmp_path / "ev" / "pr_curve.png").is_file()
    assert "merge P" in result.output and "Merge rule:" in result.output


def test_twin_frames_are_reported_apart_when_the_data_set_declares_them(tmp_path, detour_dataset):
    """``dataset.json`` ``twins``: each row gains ``twin_frames`` / ``twin_merged`` /
    ``twin_merged_wrong``, counted on the declared frames; without it, no such keys."""
    plain = run_evaluation(Dataset.open(detour_dataset), tmp_path / "plain", MapConfig(dim=DIM),
                           EvalOptions(protocol="lifelong"))
    assert all("twin_frames" not in row for row in [*plain["queries"], plain["overall"]])
    info = json.loads((detour_dataset / "dataset.json").read_text())
    # All of c-detour declared twin; b-autumn's first 30 frames.
    info["twins"] = {"b-autumn": [[0, 30]], "c-detour": [[0, FRAMES + DETOUR]]}
    (detour_dataset / "dataset.json").write_text(json.dumps(info))
    results = run_evaluation(Dataset.open(detour_dataset), tmp_path / "twins",
                             MapConfig(dim=DIM), EvalOptions(protocol="lifelong"))
    autumn, detour = results["queries"]
    assert (autumn["twin_frames"], detour["twin_frames"]) == (30, FRAMES + DETOUR)
    assert 0 <= autumn["twin_merged"] <= 30
    assert detour["merged_decisions"] > 0
    assert detour["twin_merged"] == detour["merged_decisions"]
    wrong = round(detour["merged_decisions"] * (1 - detour["merge_precision"]))
    assert detour["twin_merged_wrong"] == wrong
    overall = results["overall"]
    for key in ("twin_frames", "twin_merged", "twin_merged_wrong"):
        assert overall[key] == autumn[key] + detour[key]
    # The other keys do not change.
    for a, b in zip(plain["queries"], results["queries"], strict=True):
        assert {k: v for k, v in a.items() if k not in ("retrieval_ms", "hmm_ms")} == {
            k: v for k, v in b.items()
            if k not in ("retrieval_ms", "hmm_ms") and not k.startswith("twin_")}
