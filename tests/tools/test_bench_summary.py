"""tools/bench_summary.py: a kept-everything map, its summary, fresh drives on both."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tools import bench_summary


def test_quick_run_summarises_and_scores_both_maps(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "summary.json"
    assert bench_summary.main(["--quick", "--world", "easy", "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    (seed,) = data["seeds"]
    report = seed["summary"]
    assert report["vertices_before"] == 8 * 60 == seed["everything"]["vertices"]
    assert report["vertices_after"] == seed["summarised"]["vertices"] < 8 * 60  # some went
    assert seed["check_ok"] and seed["traversals_worth"] == round(report["vertices_after"] / 60, 1)
    for label in ("everything", "summarised"):
        scored = seed[label]
        assert scored["frames_with_match"] > 0
        assert scored["sprint_recall@1"] == round(
            scored["sprint_correct"] / scored["frames_with_match"], 4)
    assert seed["recall_change_points"] == round(
        100 * (seed["summarised"]["sprint_recall@1"] - seed["everything"]["sprint_recall@1"]), 1)
    assert seed["summarised"]["disk_bytes"] < seed["everything"]["disk_bytes"]
    assert "summarised - everything" in capsys.readouterr().out
