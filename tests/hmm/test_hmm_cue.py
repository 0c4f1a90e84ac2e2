"""Another cue's weights in the HMM (GNSS): observation, filter and smoother."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sprint_map.hmm import HMMConfig, MemoryGraphSource, SprintFilter
from sprint_map.hmm.observation import ObservationModel
from sprint_map.hmm.smoother import ForwardBackward


def test_weights_multiply_the_likelihoods():
    ids, dists = np.array([4, 9, 4, -1]), np.array([0.2, 0.5, 0.1, 0.0])
    plain = ObservationModel(HMMConfig()).evaluate(ids, dists)
    vids, _, lik, sink, _ = ObservationModel(HMMConfig()).evaluate(
        ids, dists, np.array([0.5, 0.25, 2.0, 1.0]), 3.0)
    assert vids == plain[0] == [4, 9]
    # a repeated id keeps the weight of the entry kept (the nearer one)
    assert lik == pytest.approx([plain[2][0] * 2.0, plain[2][1] * 0.25])
    assert sink == pytest.approx(plain[3] * 3.0)
    same = ObservationModel(HMMConfig()).evaluate(ids, dists, None, 1.0)
    assert same == plain


@pytest.mark.parametrize(("weights", "sink"), [(np.array([1.0, 0.0]), 1.0),
                                               (np.array([1.0]), 1.0),
                                               (np.array([1.0, np.nan]), 1.0),
                                               (None, 0.0), (None, math.inf)])
def test_bad_weights_are_refused(weights, sink):
    with pytest.raises(ValueError):
        ObservationModel(HMMConfig()).evaluate(np.array([1, 2]), np.array([0.1, 0.2]),
                                               weights, sink)


def test_weights_decide_between_identical_twins():
    """Two sequences of identical images: the hits tie, the weights decide (causal and
    smoothed), and a twin ruled out is no rival of the contrast."""
    cfg = HMMConfig()
    src = MemoryGraphSource([60, 60])
    f = SprintFilter(cfg, src)
    fb = ForwardBackward(cfg, src)
    for t in range(30):
        ids = np.array([10 + t, 70 + t])
        dists = np.array([0.1, 0.1])
        w = np.array([math.exp(-8.0), 1.0])
        d = f.step(ids, dists, w)
        fb.forward(ids, dists, w)
    assert d.seq_id == 1
    smoothed = fb.decisions()
    assert all(s.seq_id == 1 for s in smoothed[2:])
    assert all(s.contrast < 1.0 for s in smoothed[5:25])  # the twin does not count
    plain = ForwardBackward(cfg, src)
    for t in range(30):
        plain.forward(np.array([10 + t, 70 + t]), np.array([0.1, 0.1]))
    assert all(s.contrast >= 1.0 for s in plain.decisions()[5:25])


def test_sink_weight_raises_the_unmapped_place():
    cfg = HMMConfig()
    src = MemoryGraphSource([60])
    plain, weighed = SprintFilter(cfg, src), SprintFilter(cfg, src)
    for t in range(10):
        ids, dists = np.array([10 + t, 30]), np.array([0.1, 0.4])
        a = plain.step(ids, dists)
        b = weighed.step(ids, dists, None, math.exp(8.0))
    assert a.sink_prob < 0.05 < 0.9 < b.sink_prob
