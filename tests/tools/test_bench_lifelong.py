"""tools/bench_lifelong.py: the lifelong protocol, merging vs appending, on a quick run."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sprint_map.config import MapConfig
from sprint_map.frontend import GroundTruth, GroundTruthSpec
from sprint_map.localize.localizer import FrameDecision
from tools import bench_lifelong


@pytest.fixture(scope="module")
def bench() -> Any:
    return bench_lifelong


def test_score_counts_best_for_recall_and_accepted_for_precision(bench: Any) -> None:
    # Query q at x = 0, 10, 20, 30; database d at x = 0, 10, 20, 30 (same heading).
    line = np.column_stack([np.arange(4), np.arange(4) * 10.0, np.zeros(4), np.zeros(4)])
    gt = GroundTruth(GroundTruthSpec("position", radius_m=5.0, heading_deg=45.0),
                     positions={"q": line, "d": line})
    decisions = [
        FrameDecision(frame=0, seq_id=7, image_id=0, prob=0.9, best=(7, 0)),  # right, accepted
        FrameDecision(frame=1, seq_id=7, image_id=3, prob=0.9, best=(7, 3)),  # wrong, accepted
        FrameDecision(frame=2, seq_id=None, image_id=None, prob=0.2, best=(7, 2)),  # right, no
        FrameDecision(frame=3, seq_id=None, image_id=None, prob=0.1, best=None),
    ]
    has_match = np.array([True, True, True, False])
    out = bench.score(decisions, "q", gt, {7: "d"}, has_match)
    assert out["sprint_correct"] == 2 and out["sprint_recall@1"] == pytest.approx(2 / 3, abs=1e-4)
    assert (out["accepted"], out["accepted_correct"], out["precision"]) == (2, 1, 0.5)


def test_quick_run_writes_both_arms_and_halves(bench: Any, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    out_json, out_png = tmp_path / "lifelong.json", tmp_path / "lifelong.png"
    assert bench.main(["--quick", "--json", str(out_json), "--png", str(out_png)]) == 0
    data = json.loads(out_json.read_text())
    assert data["args"]["traversals"] == 8 and data["args"]["frames"] == 60
    [run] = data["seeds"]
    merge, append = run["arms"]["merge"], run["arms"]["no-merge"]
    assert [r["traversal"] for r in merge] == [r["traversal"] for r in append] == list(range(1, 8))
    assert [r["condition"] for r in merge] == ["dusk", "rain", "snow", "day", "dusk", "rain",
                                               "snow"]
    for a, b in zip(merge, append, strict=True):
        # Same map contents before each traversal: the same vertices and exact k-NN answers.
        assert a["map_vertices"] == b["map_vertices"] == 60 * a["traversal"]
        assert a["knn_recall@1"] == b["knn_recall@1"] and a["knn_recall@10"] == b["knn_recall@10"]
        assert a["knn_recall@1"] <= a["knn_recall@10"]
        assert b["edges_added"] == 0 and b["components"] == b["traversal"] + 1
        assert 0 <= a["sprint_correct"] <= a["frames_with_match"] <= a["frames"] == 60
        # Both runs score the decisions ingest makes: what the merge used, and read-only.
        assert a["ingest_differs_from_localize"] == 0
        assert 0 <= a["online_sprint_correct"] <= a["frames_with_match"]
        # Every merged decision makes two edges (both ways); appending merges none.
        assert a["edges_added"] == 2 * a["merged"] and 0 <= a["merged_wrong"] <= a["merged"]
        assert b["merged"] == b["merged_wrong"] == 0
    assert sum(r["edges_added"] for r in merge) > 0
    assert run["summary"]["ingest_differs_from_localize"] == 0
    assert merge[-1]["components"] < append[-1]["components"]
    summary = run["summary"]
    for arm, rows in (("merge", merge), ("no-merge", append)):
        earlier, later = summary[arm]["earlier"], summary[arm]["later"]
        assert earlier["traversals"] == [1, 3] and later["traversals"] == [4, 7]
        matchable = sum(r["frames_with_match"] for r in rows[3:])
        assert later["sprint_recall@1"] == pytest.approx(
            sum(r["sprint_correct"] for r in rows[3:]) / matchable, abs=1e-4)
        # The ground truth is wired to the right traversals: SPRINT finds most places.
        assert earlier["sprint_recall@1"] >= 0.4 and later["sprint_recall@1"] >= 0.4
    later = summary["merge"]["later"]
    assert later["merged"] == sum(r["merged"] for r in merge[3:]) > 0
    assert later["merge_precision"] == pytest.approx(
        1 - sum(r["merged_wrong"] for r in merge[3:]) / later["merged"], abs=1e-4)
    assert summary["no-merge"]["later"]["merge_precision"] is None
    assert summary["merge_minus_no_merge_later_points"] == pytest.approx(
        100 * (summary["merge"]["later"]["sprint_recall@1"]
               - summary["no-merge"]["later"]["sprint_recall@1"]), abs=0.01)
    assert data["mean"]["merge"]["later"]["sprint_recall@1"] == summary["merge"]["later"][
        "sprint_recall@1"]
    assert out_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    printed = capsys.readouterr().out
    assert "merge - no-merge on the later half" in printed and "no-merge R@1" in printed
    assert "merged decisions (edges): precision" in printed


def test_quick_run_on_the_latent_world(bench: Any, tmp_path: Path) -> None:
    """``--world latent``: the other family's drives (descriptors, no thumbnails), both arms."""
    out_json = tmp_path / "lifelong.json"
    assert bench.main(["--quick", "--world", "latent", "--json", str(out_json)]) == 0
    data = json.loads(out_json.read_text())
    assert data["world"] == "latent" and data["map_config"]["dim"] == 256
    assert data["city"]["grid"] == [4, 4]  # the latent-lifelong preset
    [run] = data["seeds"]
    merge, append = run["arms"]["merge"], run["arms"]["no-merge"]
    assert [r["condition"] for r in merge] == ["overcast", "dusk", "rain", "night", "snow",
                                               "day", "overcast"]
    for a, b in zip(merge, append, strict=True):
        assert a["map_vertices"] == b["map_vertices"] == 60 * a["traversal"]
        assert a["knn_recall@1"] == b["knn_recall@1"]
        assert a["ingest_differs_from_localize"] == 0 and b["edges_added"] == 0
    assert sum(r["frames_with_match"] for r in merge) > 0


def test_quick_run_with_admission_reports_the_map_size(bench: Any, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]
                                                       ) -> None:
    """``--admission``: the merge run again on a map that stores only what it lacks."""
    out_json, out_png = tmp_path / "lifelong.json", tmp_path / "grow.png"
    assert bench.main(["--quick", "--world", "latent", "--admission", "--json", str(out_json),
                       "--png", str(out_png)]) == 0
    [run] = json.loads(out_json.read_text())["seeds"]
    merge, novel = run["arms"]["merge"], run["arms"][bench.NOVEL_ARM]
    assert [r["traversal"] for r in novel] == [r["traversal"] for r in merge]
    before = 60  # the first drive, stored whole
    for a, b in zip(merge, novel, strict=True):
        assert b["map_vertices"] == before and 0 <= b["frames_stored"] <= b["frames"] == 60
        assert b["map_vertices_after"] == b["map_vertices"] + b["frames_stored"]
        before = b["map_vertices_after"]
        assert a["frames_stored"] == 60 and b["map_vertices"] <= a["map_vertices"]
        assert b["frame_ms"] > 0 and b["disk_bytes"] > 0
    assert sum(r["frames_stored"] for r in novel) <= sum(r["frames_stored"] for r in merge)
    size = run["summary"]["admission"]
    assert size["vertices"] == novel[-1]["map_vertices_after"] <= size["vertices_all"] == 480
    assert size["traversals_worth"] == pytest.approx(size["vertices"] / 60, abs=0.01)
    assert size["reingest_stored_fraction"] <= 0.05  # the last drive again: (almost) nothing
    earlier = novel[-1]["reingest_stored_earlier"]  # drives 2, 4 and 6 again, each on a copy
    assert list(earlier) == [merge[i - 1]["name"] for i in (2, 4, 6)]
    assert size["reingest_earlier_stored_fraction"] == pytest.approx(
        sum(earlier.values()) / 3 / 60, abs=1e-4)
    assert set(run["summary"]["novel_minus_merge_later_points"]) == {
        "sprint_recall@1", "accepted_recall@1", "merge_precision"}
    assert out_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "merge+novel (admission):" in capsys.readouterr().out


def test_an_admitted_map_that_learns_is_ingested_again(bench: Any, tmp_path: Path) -> None:
    """Admission and learning together: the re-ingests find the arm's own map."""
    drives, gt, _ = bench.latent_drives(0, 8, 60, bench.LATENT)
    config = MapConfig(dim=bench.LATENT.dim).replace(admission={"mode": "novel"})
    rows = bench.run_arm(drives, gt, True, tmp_path, config, learn_every=2)
    assert bench.arm_name(True, 2, config) == "merge-learn-novel"
    assert (tmp_path / "merge-learn-novel.map").is_dir()
    assert 0 <= rows[-1]["reingest_stored"] <= 60
    assert list(rows[-1]["reingest_stored_earlier"]) == [drives[i].name for i in (2, 4, 6)]
    assert [r["learned"]["adopted"] for r in rows if "learned" in r] == [False] * 3
