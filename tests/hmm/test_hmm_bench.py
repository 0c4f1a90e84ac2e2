"""tools/bench_fig4.py and bench_update_instructions.py run end to end on tiny configurations."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from typing import Any

import pytest

TOOLS = Path(__file__).resolve().parents[2] / "tools"


def load_tool(name: str) -> Any:
    spec = importlib.util.spec_from_file_location(name, TOOLS / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_bench_fig4_writes_json_and_png(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bench = load_tool("bench_fig4")
    out_json, out_png = tmp_path / "fig4.json", tmp_path / "fig4.png"
    assert bench.main(["--json", str(out_json), "--png", str(out_png), "--runs", "2",
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


def test_bench_update_instructions_subtracts_the_empty_run(tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """The driven program runs; the table is (count with frames - count without) / frames.

    (valgrind itself is not run here: under it a Python start-up with numpy takes ~30 s.)
    """
    tool = load_tool("bench_update_instructions")
    tool.drive(2000, 100, 150)  # the measured program, for real (it crosses sequences)
    calls: list[list[str]] = []

    def fake_run(cmd: list[str], **kwargs: Any) -> Any:
        calls.append(cmd)
        frames = int(cmd[-1])
        refs = 1_000_000 + 40_000 * frames
        return type("Done", (), {"stderr": f"==1== I   refs:      {refs:,}\n"})()

    monkeypatch.setattr(tool.subprocess, "run", fake_run)
    out = tmp_path / "instr.json"
    assert tool.main(["--nodes", "2000", "--frames", "200", "--seq-len", "100", "1000",
                      "--json", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [(r["seq_len"], r["instructions_per_update"]) for r in rows] == [(100, 40_000),
                                                                            (1000, 40_000)]
    assert calls[0][:2] == ["valgrind", "--tool=callgrind"]
    assert [c[-4:] for c in calls[:2]] == [["--child", "2000", "100", "200"],
                                           ["--child", "2000", "100", "0"]]
