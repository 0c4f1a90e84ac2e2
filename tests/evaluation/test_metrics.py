"""Place-recognition metrics."""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.evaluation.metrics import pr_curve, recall_at_k


def test_recall_at_k_leaves_out_frames_without_a_match():
    correct = np.array([[False, True], [True, False], [False, False], [True, True]])
    has_match = np.array([True, True, True, False])
    assert recall_at_k(correct, has_match, (1, 2)) == {1: pytest.approx(1 / 3),
                                                        2: pytest.approx(2 / 3)}


def test_pr_curve_by_hand():
    scores = np.array([0.9, 0.8, 0.7, 0.6])
    correct = np.array([True, False, True, True])
    has_match = np.array([True, True, True, True])
    curve = pr_curve(scores, correct, has_match)
    np.testing.assert_allclose(curve.precision, [1, 0.5, 2 / 3, 0.75])
    np.testing.assert_allclose(curve.recall, [0.25, 0.25, 0.5, 0.75])
    assert curve.recall_at_full_precision == pytest.approx(0.25)
    assert 0 < curve.auc < 1


def test_pr_curve_ties_form_one_point_and_novel_answers_are_false_positives():
    scores = np.array([0.5, 0.5, 0.2])
    correct = np.array([True, True, True])
    has_match = np.array([True, False, True])  # frame 1 has no true match: a false positive
    curve = pr_curve(scores, correct, has_match)
    np.testing.assert_allclose(curve.thresholds, [0.5, 0.2])
    np.testing.assert_allclose(curve.precision, [0.5, 2 / 3])
    np.testing.assert_allclose(curve.recall, [0.5, 1.0])


def test_perfect_ranking_has_auc_one():
    curve = pr_curve(np.linspace(1, 0, 10), np.ones(10, bool), np.ones(10, bool))
    assert curve.auc == pytest.approx(1.0)
    assert curve.recall_at_full_precision == 1.0
