"""tools/bench_fig4.py runs end to end on a tiny configuration."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tools import bench_fig4


def test_bench_fig4_writes_json_and_png(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out_json, out_png = tmp_path / "fig4.json", tmp_path / "fig4.png"
    assert bench_fig4.main(["--json", str(out_json), "--png", str(out_png), "--runs", "2",
                       "--steps", "30", "--max-nodes", "10000"]) == 0
    rows = json.loads(out_json.read_text())["rows"]
    assert [(r["nodes"], r["seq_len"]) for r in rows] == [
        (100, 100), (1000, 100), (1000, 1000), (10000, 100), (10000, 1000), (10000, 10000)]
    for row in rows:
        assert row["full_ms"] > 0 and row["sprint_ms"] > 0
        assert row["speedup"] == pytest.approx(row["full_ms"] / row["sprint_ms"])
        # Only the sequence the query is on (plus the previous one just after a boundary).
        assert row["sprint_active_vertices"] <= 2 * row["seq_len"]
    assert out_png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "speedup" in capsys.readouterr().out
