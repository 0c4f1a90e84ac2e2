"""Place-recognition metrics over per-frame answers (pure numpy, no map).

Conventions (also in ``docs/frontend.md``, "Evaluation"):

- *recall@k* counts the query frames that have a true match in the database and whose answer
  (the k-NN list, or SPRINT's most probable place) contains one. Frames with no true match
  (a street never driven before) are left out of recall: nothing could be right for them.
- The *precision-recall curve* sweeps a threshold over SPRINT's decision probability: a frame is
  *answered* when its best place's probability reaches the threshold; an answer is a true
  positive when it is correct. Precision is over answered frames (including frames without a
  true match, whose answers are false positives by definition); recall over frames with a match.
- *Merge metrics* (:func:`merge_metrics`) score the decisions the merge rule selects as edges:
  a merged decision is correct when its place is a true match (a merged decision on a frame
  without one is wrong by definition); every merged decision makes the same number of edges
  (2 when edges are stored both ways), and an edge is wrong when its decision is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["MergeMetrics", "PRCurve", "merge_metrics", "percentiles", "pr_curve", "recall_at_k"]


def recall_at_k(correct: np.ndarray, has_match: np.ndarray, ks: tuple[int, ...]
                ) -> dict[int, float]:
    """k-NN recall: ``correct`` is (Q, K) bool over ranked hits, ``has_match`` (Q,) bool."""
    out = {}
    denom = max(int(has_match.sum()), 1)
    for k in ks:
        hit = correct[:, :k].any(axis=1) & has_match
        out[k] = float(hit.sum()) / denom
    return out


@dataclass(frozen=True)
class PRCurve:
    """Precision and recall at every distinct threshold, highest threshold first."""

    thresholds: np.ndarray
    precision: np.ndarray
    recall: np.ndarray

    @property
    def auc(self) -> float:
        """Area under the curve (trapezoids over recall, starting from recall 0)."""
        if not len(self.recall):
            return 0.0
        r = np.r_[0.0, self.recall]
        p = np.r_[self.precision[0], self.precision]
        return float(np.sum(np.diff(r) * (p[1:] + p[:-1]) / 2))

    @property
    def recall_at_full_precision(self) -> float:
        """Highest recall reached while precision is still exactly 1."""
        ok = self.precision >= 1.0
        return float(self.recall[ok].max()) if ok.any() else 0.0


def pr_curve(scores: np.ndarray, correct: np.ndarray, has_match: np.ndarray) -> PRCurve:
    """Precision-recall of answers ranked by ``scores``.

    Parameters
    ----------
    scores : (Q,) float
        Confidence of each frame's best answer.
    correct : (Q,) bool
        Whether that answer is a true match.
    has_match : (Q,) bool
        Whether the frame has any true match in the database.

    Notes
    -----
    O(Q log Q).
    """
    order = np.argsort(-scores, kind="stable")
    s = scores[order]
    tp = np.cumsum(correct[order] & has_match[order])
    answered = np.arange(1, len(s) + 1)
    # One point per distinct threshold: the last index of each run of equal scores.
    last = np.r_[np.nonzero(np.diff(s))[0], len(s) - 1] if len(s) else np.array([], int)
    denom = max(int(has_match.sum()), 1)
    return PRCurve(
        thresholds=s[last],
        precision=tp[last] / answered[last],
        recall=tp[last] / denom,
    )


@dataclass(frozen=True)
class MergeMetrics:
    """How good the edges of one drive's merge are (see :func:`merge_metrics`).

    Attributes
    ----------
    precision : float
        Fraction of merged decisions that are correct (1.0 when nothing is merged: no edge is
        wrong; read it with ``recall``).
    recall : float
        Merged correct decisions over frames with a true match (0.0 when no frame has one).
    edges_added, edges_wrong : int
        Edges the merged decisions make, and how many of them come from a wrong decision.
    novel_merged : float
        Fraction of the frames without a true match whose decision was merged (0.0 when every
        frame has one).
    merged, merged_correct : int
        Merged decisions, and how many of them are correct.
    """

    precision: float
    recall: float
    edges_added: int
    edges_wrong: int
    novel_merged: float
    merged: int
    merged_correct: int


def merge_metrics(merged: np.ndarray, correct: np.ndarray, has_match: np.ndarray,
                  edges_per_decision: int = 2) -> MergeMetrics:
    """Score the decisions a merge rule selects.

    Parameters
    ----------
    merged : (Q,) bool
        Which decisions the merge rule selects (become edges).
    correct : (Q,) bool
        Whether each decision's place is a true match for its frame.
    has_match : (Q,) bool
        Whether the frame has any true match in the map.
    edges_per_decision : int
        Edges one merged decision makes: 2 when stored both ways, else 1.

    Returns
    -------
    MergeMetrics

    Examples
    --------
    >>> m = merge_metrics(np.array([True, True, False, True]), np.array([True, False, True, False]),
    ...                   np.array([True, True, True, False]))
    >>> m.precision, m.recall, m.edges_added, m.edges_wrong, m.novel_merged
    (0.3333333333333333, 0.3333333333333333, 6, 4, 1.0)
    """
    merged = np.asarray(merged, dtype=bool)
    has_match = np.asarray(has_match, dtype=bool)
    good = merged & np.asarray(correct, dtype=bool) & has_match
    n_merged, n_good = int(merged.sum()), int(good.sum())
    n_match, n_novel = int(has_match.sum()), int((~has_match).sum())
    return MergeMetrics(
        precision=n_good / n_merged if n_merged else 1.0,
        recall=n_good / n_match if n_match else 0.0,
        edges_added=n_merged * edges_per_decision,
        edges_wrong=(n_merged - n_good) * edges_per_decision,
        novel_merged=int((merged & ~has_match).sum()) / n_novel if n_novel else 0.0,
        merged=n_merged,
        merged_correct=n_good,
    )


def percentiles(values: list[float] | np.ndarray, qs: tuple[int, ...] = (50, 90, 99)
                ) -> dict[str, float]:
    """Percentiles ``qs`` of ``values``, rounded, as ``{"p50": ...}`` (zeros when empty)."""
    arr = np.asarray(values, dtype=float)
    if not len(arr):
        return {f"p{q}": 0.0 for q in qs}
    return {f"p{q}": round(float(np.percentile(arr, q)), 4) for q in qs}
