"""tools/bench_fleet.py on a small synthetic map: every row measured, answers checked."""

from __future__ import annotations

import json

import pytest

from tools import bench_fleet


@pytest.mark.slow
def test_quick_run_writes_every_row(tmp_path, capsys):
    bench = bench_fleet
    out = tmp_path / "fleet.json"
    code = bench.main(["--quick", "--vehicles", "3", "--frames", "15", "--overload", "6",
                       "--drives", "3", "--drive-frames", "40", "--dim", "16",
                       "--ingest-repeats", "2", "--json", str(out)])
    assert code == 0, capsys.readouterr()
    data = json.loads(out.read_text())
    service = {(r["mode"], r["vehicles"]): r for r in data["service"]}
    assert set(service) == {("batched", 3), ("one-at-a-time", 3), ("overload (32 admitted)", 6)}
    for mode in ("batched", "one-at-a-time"):
        row = service[(mode, 3)]
        assert row["frames"] == 45 and row["errors"] == 0 and row["offline_equal"] == "45/45"
        assert row["statuses"] == {"200": 45} and row["frames_per_s"] > 0
    assert not any(code.startswith("5") and code != "503"
                   for r in data["service"] for code in r["statuses"])
    hows = {(r["what"], r["how"]) for r in data["ingest"]}
    assert len(hows) == 8 and all(r["frames"] == 120 for r in data["ingest"])
    for r in data["ingest"]:  # appended: the median of the repeats; localised: one run
        assert r["runs"] == (1 if "localised" in r["what"] else 2 if "in process" in r["what"]
                             else 1)
        assert r["min_s"] <= r["seconds"] <= r["max_s"]
    assert "frames_per_s" in capsys.readouterr().out
