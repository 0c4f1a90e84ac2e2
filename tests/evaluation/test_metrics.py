"""Place-recognition metrics."""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.evaluation.metrics import merge_metrics, pr_curve, recall_at_k


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


def test_merge_metrics_by_hand():
    # frames: 0 merged right; 1 merged wrong; 2 right but not merged; 3 novel, merged;
    # 4 novel, not merged; 5 "correct" flag on a frame without a match still counts as wrong
    merged = np.array([True, True, False, True, False, True])
    correct = np.array([True, False, True, False, False, True])
    has_match = np.array([True, True, True, False, False, False])
    m = merge_metrics(merged, correct, has_match, edges_per_decision=2)
    assert (m.merged, m.merged_correct) == (4, 1)
    assert m.precision == pytest.approx(1 / 4)
    assert m.recall == pytest.approx(1 / 3)
    assert (m.edges_added, m.edges_wrong) == (8, 6)
    assert m.novel_merged == pytest.approx(2 / 3)
    one_way = merge_metrics(merged, correct, has_match, edges_per_decision=1)
    assert (one_way.edges_added, one_way.edges_wrong) == (4, 3)


def test_merge_metrics_when_nothing_is_merged_or_nothing_is_novel():
    nothing = merge_metrics(np.zeros(3, bool), np.ones(3, bool), np.ones(3, bool))
    assert (nothing.precision, nothing.recall, nothing.edges_added, nothing.novel_merged) == (
        1.0, 0.0, 0, 0.0)
    all_novel = merge_metrics(np.array([True, False]), np.ones(2, bool), np.zeros(2, bool))
    assert (all_novel.precision, all_novel.recall, all_novel.novel_merged) == (0.0, 0.0, 0.5)
    assert all_novel.edges_wrong == all_novel.edges_added == 2
