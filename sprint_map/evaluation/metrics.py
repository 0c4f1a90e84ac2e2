"""Place-recognition metrics over per-frame answers (pure numpy, no map).

Conventions (also in ``docs/architecture.md``, "Evaluation"):

- *recall@k* counts the query frames that have a true match in the database and whose answer
  (the k-NN list, or SPRINT's most probable place) contains one. Frames with no true match
  (a street never driven before) are left out of recall: nothing could be right for them.
- The *precision-recall curve* sweeps a threshold over SPRINT's decision probability: a frame is
  *answered* when its best place's probability reaches the threshold; an answer is a true
  positive when it is correct. Precision is over answered frames (including frames without a
  true match, whose answers are false positives by definition); recall over frames with a match.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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


def percentiles(values: list[float] | np.ndarray, qs: tuple[int, ...] = (50, 90, 99)
                ) -> dict[str, float]:
    arr = np.asarray(values, dtype=float)
    if not len(arr):
        return {f"p{q}": 0.0 for q in qs}
    return {f"p{q}": round(float(np.percentile(arr, q)), 4) for q in qs}
