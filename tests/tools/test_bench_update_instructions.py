"""tools/bench_update_instructions.py: the driven program runs, the count is subtracted."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from tools import bench_update_instructions


def test_bench_update_instructions_subtracts_the_empty_run(tmp_path: Path,
                                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """The driven program runs; the table is (count with frames - count without) / frames.

    (valgrind itself is not run here: under it a Python start-up with numpy takes ~30 s.)
    """
    bench_update_instructions.drive(2000, 100, 150)  # the measured program, for real (it crosses sequences)
    calls: list[list[str]] = []

    def fake_run(cmd: list[str], **kwargs: Any) -> Any:
        calls.append(cmd)
        frames = int(cmd[-1])
        refs = 1_000_000 + 40_000 * frames
        return type("Done", (), {"stderr": f"==1== I   refs:      {refs:,}\n"})()

    monkeypatch.setattr(bench_update_instructions.subprocess, "run", fake_run)
    out = tmp_path / "instr.json"
    assert bench_update_instructions.main(["--nodes", "2000", "--frames", "200", "--seq-len", "100", "1000",
                      "--json", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    assert [(r["seq_len"], r["instructions_per_update"]) for r in rows] == [(100, 40_000),
                                                                            (1000, 40_000)]
    assert calls[0][:2] == ["valgrind", "--tool=callgrind"]
    assert [c[-4:] for c in calls[:2]] == [["--child", "2000", "100", "200"],
                                           ["--child", "2000", "100", "0"]]
