"""End to end on synthetic multi-traversal data: temporal inference against k-NN retrieval."""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.hmm import FullGraphFilter, HMMConfig, SprintFilter
from tests.helpers.hmm_synth import Scenario, make_scenario


def run(scenario: Scenario, filt: SprintFilter | FullGraphFilter, k: int = 10
        ) -> dict[str, float]:
    ids, dists = scenario.knn(k)
    n = len(ids)
    correct = np.zeros(n, dtype=bool)
    no_match = np.zeros(n, dtype=bool)
    active = []
    for i in range(n):
        decision = filt.step(ids[i], dists[i])
        no_match[i] = decision.vertex_id is None
        correct[i] = decision.vertex_id is not None and scenario.correct(i, decision.vertex_id)
        active.append(decision.n_active_vertices)
    known = ~scenario.novel
    knn1 = np.array([scenario.correct(i, int(ids[i, 0])) for i in range(n)])
    return {
        "knn1": float(knn1[known].mean()),
        "accuracy": float(correct[known].mean()),
        "novel_no_match": float(no_match[scenario.novel].mean()),
        "known_no_match": float(no_match[known].mean()),
        "active": float(np.mean(active)),
    }


@pytest.fixture(scope="module", params=[11, 12, 13])
def scenario(request: pytest.FixtureRequest) -> Scenario:
    # Noise chosen so that single-frame retrieval is weak (k-NN@1 around 40 %).
    return make_scenario(request.param, noise=1.5, change=0.5)


def test_temporal_inference_beats_knn_and_flags_novel_streets(scenario: Scenario) -> None:
    result = run(scenario, SprintFilter(HMMConfig(), scenario.source))
    assert 0.25 < result["knn1"] < 0.6, result          # the data is hard for one frame...
    assert result["accuracy"] >= result["knn1"] + 0.25, result   # ...and easy for a sequence
    assert result["accuracy"] >= 0.7, result
    assert result["novel_no_match"] >= 0.8, result
    assert result["known_no_match"] <= 0.15, result


def test_pruned_sprint_answers_like_the_full_graph(scenario: Scenario) -> None:
    """Pruning at 1e-4 changes (almost) no decision on realistic data."""
    sprint = run(scenario, SprintFilter(HMMConfig(), scenario.source))
    full = run(scenario, FullGraphFilter(HMMConfig(), scenario.source))
    assert abs(sprint["accuracy"] - full["accuracy"]) <= 0.02
    assert abs(sprint["novel_no_match"] - full["novel_no_match"]) <= 0.05


def test_recovers_after_the_turn_and_after_the_novel_stretch() -> None:
    scenario = make_scenario(21, noise=1.5, change=0.5)
    ids, dists = scenario.knn(10)
    filt = SprintFilter(HMMConfig(), scenario.source)
    correct = []
    for i in range(len(ids)):
        decision = filt.step(ids[i], dists[i])
        correct.append(decision.vertex_id is not None and scenario.correct(i, decision.vertex_id))
    route = scenario.query_place // 150
    turn = int(np.flatnonzero(route == 1)[0])
    back = int(np.flatnonzero(route == 2)[0])
    # Localised again within 15 frames of the turn and of leaving the novel stretch, and
    # mostly right over the 20 frames after that.
    for start in (turn, back):
        assert any(correct[start: start + 15])
        assert np.mean(correct[start + 15: start + 35]) >= 0.7
