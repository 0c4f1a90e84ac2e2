"""The observation model: likelihood ratios, the adaptive kernel scale, novelty."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sprint_map.hmm import HMMConfig, MemoryGraphSource, ObservationModel, SprintFilter


def test_fixed_scale_likelihoods_by_hand() -> None:
    model = ObservationModel(HMMConfig(dist_scale=0.1, miss_margin=1.0, novelty_margin=0.25))
    obs = model.observe(np.array([4, -1, 7, 4]), np.array([0.3, 1.0, 0.5, 0.2]))
    assert obs.vertex_ids == [4, 7] and obs.distances == [0.2, 0.5]
    assert obs.lik == pytest.approx([math.exp(3.0 + 1.0), math.exp(1.0)])
    assert obs.sink_lik == pytest.approx(math.exp(0.25))
    assert obs.scale == 0.1


def test_novelty_dist_scores_the_sink_like_a_hit_at_that_distance() -> None:
    model = ObservationModel(HMMConfig(dist_scale=0.1, novelty_dist=0.4))
    near = model.observe(np.array([1, 2]), np.array([0.3, 0.5]))
    assert near.sink_lik == pytest.approx(math.exp(0.25))      # d_1 < novelty_dist
    far = model.observe(np.array([1, 2]), np.array([0.6, 0.8]))
    assert far.sink_lik == pytest.approx(math.exp((0.8 - 0.4) / 0.1 + 1.0))
    assert far.sink_lik > max(far.lik)


def test_adaptive_scale_follows_the_spread_of_the_hits() -> None:
    config = HMMConfig(dist_scale_ema=0.5, dist_scale_factor=0.5)
    model = ObservationModel(config)
    assert model.scale is None
    model.observe(np.array([1]), np.array([0.3]))                  # one hit: no spread yet
    assert model.scale is None
    model.observe(np.array([1, 2]), np.array([0.3, 0.5]))
    assert model.scale == pytest.approx(0.5 * 0.2)
    model.observe(np.array([1, 2]), np.array([0.3, 0.7]))
    assert model.scale == pytest.approx(0.5 * (0.2 + 0.5 * (0.4 - 0.2)))
    model.reset()
    assert model.scale is None


@pytest.mark.parametrize("factor", [0.1, 7.0])
def test_adaptive_filter_is_invariant_to_the_distance_scale(factor: float) -> None:
    """HoG-like and patchnorm-like distances give the same belief with the default kernel."""
    rng = np.random.default_rng(5)
    source = MemoryGraphSource([40, 40, 40])
    a = SprintFilter(HMMConfig(), source)
    b = SprintFilter(HMMConfig(), source)
    for t in range(30):
        ids = np.append(t, rng.integers(0, 120, size=4))
        dists = np.sort(rng.uniform(0.2, 0.4, size=5))
        a.step(ids, dists)
        b.step(ids, dists * factor)
    np.testing.assert_allclose(a.posterior()[1], b.posterior()[1], atol=1e-10)
    da, db = a.decide(), b.decide()
    assert da.candidate_id == db.candidate_id and da.vertex_id == db.vertex_id
    assert da.prob == pytest.approx(db.prob, abs=1e-10)


@pytest.mark.parametrize(("ids", "dists", "expected"), [
    (np.array([7]), np.array([0.3]), 7),
    (np.array([7], dtype=np.uint32), np.array([0.0], dtype=np.float32), 7),
    (np.array([0]), np.array([2.5]), 0),
    ([7], [0.3], -1),                                   # not arrays
    (np.array([[7]]), np.array([[0.3]]), -1),           # (1, 1)
    (np.array([7]), np.array([[0.3]]), -1),             # shapes differ
    (np.array([7, 8]), np.array([0.3, 0.4]), -1),       # two hits
    (np.array([], dtype=np.int64), np.array([]), -1),
    (np.array([-1]), np.array([0.3]), -1),              # padding only
    (np.array([7.0]), np.array([0.3]), -1),             # float ids
    (np.array([True]), np.array([0.3]), -1),
    (np.array([7]), np.array([np.nan]), -1),
    (np.array([7]), np.array([-1e-7]), -1),             # clipped by evaluate
])
def test_single_hit_accepts_exactly_the_plain_frames(ids: object, dists: object,
                                                     expected: int) -> None:
    model = ObservationModel(HMMConfig())
    assert model.single_hit(ids, dists) == expected  # type: ignore[arg-type]
    if expected >= 0:  # its constants are what evaluate computes for the frame
        vids, _, lik, sink_lik, _ = model.evaluate(ids, dists)  # type: ignore[arg-type]
        assert (vids, lik, sink_lik) == ([expected], [model.one_hit_lik], model.sink_lik_const)


def test_single_hit_is_off_with_novelty_dist() -> None:
    model = ObservationModel(HMMConfig(novelty_dist=0.5))
    assert model.single_hit(np.array([3]), np.array([0.1])) == -1
