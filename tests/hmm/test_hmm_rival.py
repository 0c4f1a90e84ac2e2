"""The drive rival (``HMMConfig.rival_reach``, issue 51): a hit's advantage is measured from its
own drive's nearest far-away hit, so a drive close to the frame everywhere (a condition) gains
nothing and a drive with a sharp minimum (a place) keeps its ratio."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sprint_map.hmm import (
    FullGraphFilter,
    HMMConfig,
    MemoryGraphSource,
    ObservationModel,
    SprintFilter,
)
from sprint_map.hmm.observation import sequence_first_of


def test_rival_likelihoods_by_hand() -> None:
    source = MemoryGraphSource([100, 100])
    model = ObservationModel(HMMConfig(dist_scale=0.1, rival_reach=10), source.sequence_first)
    # drive 0: images 5 and 60 (rivals of each other); drive 1: images 50 and 51 (one place)
    obs = model.observe(np.array([5, 60, 150, 151, 199]),
                        np.array([0.5, 0.5, 0.45, 0.46, 0.6]))
    # d_far = 0.6: 199 is a rival of 150 and 151, but farther than them (no advantage lost)
    assert obs.lik == pytest.approx([math.e, math.e, math.exp(1.5 + 1.0), math.exp(1.4 + 1.0),
                                     math.e])
    plain = ObservationModel(HMMConfig(dist_scale=0.1)).observe(
        np.array([5, 60, 150, 151, 199]), np.array([0.5, 0.5, 0.45, 0.46, 0.6]))
    assert plain.lik[:2] == pytest.approx([math.exp(2.0)] * 2) and plain.lik[2:] == obs.lik[2:]


def test_rival_keeps_the_advantage_over_a_farther_rival() -> None:
    source = MemoryGraphSource([100])
    model = ObservationModel(HMMConfig(dist_scale=0.1, rival_reach=10), source.sequence_first)
    obs = model.observe(np.array([10, 50, 90]), np.array([0.2, 0.4, 0.6]))
    # 10's nearest far-away rival is 50 (0.4): advantage 0.2; 50's is 10 (nearer): none;
    # 90's rivals are both nearer: none
    assert obs.lik == pytest.approx([math.exp(2.0 + 1.0), math.e, math.e])


def test_rival_is_off_without_a_sequence_look_up_or_a_reach() -> None:
    ids, dists = np.array([5, 60, 150]), np.array([0.5, 0.5, 0.45])
    off = ObservationModel(HMMConfig(dist_scale=0.1)).observe(ids, dists).lik
    assert ObservationModel(HMMConfig(dist_scale=0.1, rival_reach=10)).observe(
        ids, dists).lik == off
    source = MemoryGraphSource([100, 100])
    assert ObservationModel(HMMConfig(dist_scale=0.1), source.sequence_first).observe(
        ids, dists).lik == off
    assert sequence_first_of(object()) is None
    assert sequence_first_of(source) == source.sequence_first


def test_rivals_are_read_among_the_k_nearest_only() -> None:
    source = MemoryGraphSource([100])
    config = HMMConfig(dist_scale=0.1, rival_reach=10, k=2)
    model = ObservationModel(config, source.sequence_first)
    # a deep pass: 3 hits, k = 2. 80 would be 10's rival, but it is not among the 2 nearest.
    obs = model.observe(np.array([10, 11, 80]), np.array([0.2, 0.25, 0.3]))
    assert obs.lik == pytest.approx([math.exp(1.0 + 1.0), math.exp(0.5 + 1.0), math.e])


def test_config_validates_rival_reach() -> None:
    assert HMMConfig().rival_reach == 0
    assert HMMConfig.from_dict(HMMConfig(rival_reach=7).to_dict()).rival_reach == 7
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="rival_reach"):
            HMMConfig(rival_reach=bad)  # type: ignore[arg-type]


def condition_frames(rng: np.random.Generator, frames: int
                     ) -> list[tuple[np.ndarray, np.ndarray]]:
    """A query driven along drive 1 (vertices 200..399) from image 20: each frame retrieves its
    place on drive 1 (a sharp minimum) and, nearer still, images of drive 0 (vertices 0..199:
    the query's condition, close everywhere), one of them on a track as consistent as the
    place's (image 100 + t), the others scattered along the drive."""
    out = []
    for t in range(frames):
        place = 200 + 20 + t
        cond = np.append(rng.choice(np.r_[0:80, 140:200], size=4, replace=False),
                         [100 + t, 101 + t])
        ids = np.concatenate([cond, [place, place + 1, place - 1]])
        dists = np.concatenate([rng.uniform(0.30, 0.34, 4), [0.32, 0.33, 0.35, 0.37, 0.37]])
        far = 400 + int(rng.integers(0, 200))
        ids, dists = np.append(ids, far), np.append(dists, 0.5)
        order = np.argsort(dists)
        out.append((ids[order].astype(np.int64), dists[order]))
    return out


@pytest.mark.parametrize("seed", [0, 1])
def test_the_rival_answers_by_place_where_a_condition_drive_crowds_the_hits(seed: int) -> None:
    source = MemoryGraphSource([200, 200, 200])
    frames = condition_frames(np.random.default_rng(seed), 30)
    answers = {}
    for reach in (0, 10):
        flt = SprintFilter(HMMConfig(rival_reach=reach), source)
        on_place = 0
        for t, (ids, dists) in enumerate(frames):
            d = flt.step(ids, dists)
            on_place += t >= 5 and d.vertex_id is not None and abs(d.vertex_id - 220 - t) <= 2
        answers[reach] = on_place
    assert answers[10] >= 23 and answers[0] <= answers[10] - 10, answers


def test_sprint_filter_equals_full_graph_with_the_rival() -> None:
    source = MemoryGraphSource([200, 200, 200])
    config = HMMConfig(rival_reach=10, prune_threshold=0.0, support_threshold=0.0,
                       max_active_components=0)
    sprint, full = SprintFilter(config, source), FullGraphFilter(config, source)
    for ids, dists in condition_frames(np.random.default_rng(3), 15):
        sprint.step(ids, dists)
        full.step(ids, dists)
        vids, probs, sink = sprint.posterior()
        dense = np.zeros(source.n_vertices)
        dense[vids] = probs
        np.testing.assert_allclose(dense, full.posterior()[1], rtol=0, atol=1e-12)
        assert sink == pytest.approx(full.posterior()[2], abs=1e-12)
