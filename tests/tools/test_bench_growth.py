"""tools/bench_growth.py: the growth run and its lag comparison, on a tiny world."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from sprint_map.config import MapConfig
from sprint_map.map import SprintMap
from tools import bench_growth


def test_lag_timing_keeps_the_fastest_of_each_way(tmp_path: Path, monkeypatch) -> None:
    """Each way is run ``repeat`` times, alternating, and the smallest time of each is kept
    (here the clock-free part: the calls and which times win)."""
    rng = np.random.default_rng(0)
    city = bench_growth.make_city(rng, 4, 60, 16)
    with SprintMap.create(tmp_path / "m.map", MapConfig(dim=16)) as m:
        m.ingest(bench_growth.drive(rng, city, 40))
        seq = bench_growth.drive(rng, city, 30)
        calls: list[int] = []
        hmm = iter([0.5, 1.4, 0.3, 1.1, 0.4, 1.2])  # causal, lag, causal, lag, ...
        real = SprintMap.localize

        def timed(self: SprintMap, descriptors: np.ndarray, *, lag: int = 0, **kw: object):
            decisions, timing = real(self, descriptors, lag=lag, **kw)
            calls.append(lag)
            timing.hmm_ms[:] = [next(hmm)] * len(timing.hmm_ms)
            timing.retrieval_ms[:] = [0.1] * len(timing.retrieval_ms)
            return decisions, timing

        monkeypatch.setattr(SprintMap, "localize", timed)
        got = bench_growth.lag_timing(m, seq, 5, 3)
    assert calls == [0, 5, 0, 5, 0, 5]
    assert got == {"causal_ms": 0.3, "lag_ms": 1.1, "causal_total_ms": 0.4,
                   "lag_total_ms": 1.2}


def test_a_quick_run_reports_the_lag_against_the_causal_step(tmp_path: Path) -> None:
    out = tmp_path / "growth.json"
    bench_growth.main(["--sequences", "3", "--frames", "40", "--streets", "4", "--street-len",
                       "60", "--dim", "16", "--lag", "3", "--repeat", "2", "--json", str(out)])
    data = json.loads(out.read_text())
    lagged = [r for r in data["rows"] if "lag_ms" in r]
    assert [r["sequence"] for r in lagged] == [1, 2]
    for r in lagged:
        assert 0 < r["causal_ms"] <= r["causal_total_ms"]
        assert 0 < r["lag_ms"] <= r["lag_total_ms"]
    assert data["lag_vs_causal"] == np.mean([r["lag_ms"] / r["causal_ms"] for r in lagged])
