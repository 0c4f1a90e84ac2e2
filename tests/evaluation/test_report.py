"""The evaluation report's plots: the latency histogram's axis spans the data."""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.evaluation.report import latency_bins, latency_figure


def test_the_latency_axis_spans_the_data(rng):
    matplotlib = pytest.importorskip("matplotlib")
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lat = {"retrieval_ms": list(rng.uniform(0.5, 3.0, 200)),
           "hmm_ms": list(rng.uniform(0.1, 0.4, 200)) + [0.0]}  # a frame with nothing to do
    fig = latency_figure(lat, plt)
    try:
        lo, hi = fig.axes[0].get_xlim()
        assert 0.05 <= lo <= 0.1 and 3.0 <= hi <= 6.0, (lo, hi)
        counts = [sum(p.get_height() for p in container) for container in fig.axes[0].containers]
        assert counts == [200, 201]  # every frame is in the plot, the zero in the first bin
    finally:
        plt.close(fig)


def test_bins_without_data_or_with_one_value():
    assert np.all(np.diff(latency_bins([[], []])) > 0)
    one = latency_bins([[2.0], []])
    assert one[0] < 2.0 < one[-1] and one[-1] / one[0] >= 10
