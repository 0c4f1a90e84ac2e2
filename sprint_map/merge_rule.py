"""The merge rule: which localisation decisions of a drive become permanent edges.

A merged edge is permanent and carries belief for every later drive, so the rule is tuned for
precision (``docs/architecture.md``, "The merge rule"). A decision on frame ``i`` matched to
``(s, j)`` is merged when all of these hold:

1. it is confident: its place probability is at least ``merge_threshold``;
2. it is not novel: its probability of being an unmapped place (``novel_prob``) is at most
   ``merge_max_novel``;
3. it is temporally consistent: among the frames ``i - merge_window .. i + merge_window``
   (``i`` excluded), at least ``merge_min_agree`` are matched to the same sequence ``s`` at
   images that advance with the frames: for a neighbour ``i + d`` matched to ``(s, j')``,
   ``0 <= (j' - j) * sign(d) <= merge_max_rate * |d| + 1``. A vehicle on a mapped road is
   matched along it; a wrong match rarely has neighbours that agree with it.

The decisions are usually the smoothed ones (:mod:`sprint_map.hmm.smoother`): after the whole
drive has been seen, the future of the drive supports or contradicts each frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

__all__ = ["MergeDecision", "MergeRule", "select_merges"]


class MergeDecision(Protocol):
    """What the rule reads of a decision (:class:`sprint_map.localizer.FrameDecision`)."""

    @property
    def frame(self) -> int: ...
    @property
    def seq_id(self) -> int | None: ...
    @property
    def image_id(self) -> int | None: ...
    @property
    def prob(self) -> float: ...
    @property
    def novel_prob(self) -> float: ...


@dataclass(frozen=True)
class MergeRule:
    """The merge rule's parameters (fields of :class:`sprint_map.config.MapConfig`)."""

    threshold: float = 0.5
    max_novel: float = 1.0
    window: int = 0
    min_agree: int = 0
    max_rate: float = 3.0

    def to_dict(self) -> dict[str, float]:
        return {"merge_threshold": self.threshold, "merge_max_novel": self.max_novel,
                "merge_window": self.window, "merge_min_agree": self.min_agree,
                "merge_max_rate": self.max_rate}


def select_merges(decisions: Sequence[MergeDecision], rule: MergeRule) -> np.ndarray:
    """Which decisions the rule merges: a boolean array, one entry per decision.

    ``decisions`` must be the consecutive frames of one drive, in order (``frame`` is
    ``0 .. n-1``).

    Notes
    -----
    O(n * merge_window).

    Examples
    --------
    >>> from sprint_map.localizer import FrameDecision
    >>> ds = [FrameDecision(i, 0, 10 + i, 0.9) for i in range(5)]
    >>> select_merges(ds, MergeRule(threshold=0.5, window=2, min_agree=1)).tolist()
    [True, True, True, True, True]
    >>> ds[2] = FrameDecision(2, 1, 40, 0.9)  # a jump to another drive: no neighbour agrees
    >>> select_merges(ds, MergeRule(threshold=0.5, window=2, min_agree=1)).tolist()
    [True, True, False, True, True]
    """
    n = len(decisions)
    seq = np.array([-1 if d.seq_id is None else d.seq_id for d in decisions], dtype=np.int64)
    img = np.array([-1 if d.image_id is None else d.image_id for d in decisions], dtype=np.int64)
    prob = np.array([d.prob for d in decisions], dtype=np.float64)
    novel = np.array([d.novel_prob for d in decisions], dtype=np.float64)
    ok = (seq >= 0) & (prob >= rule.threshold) & (novel <= rule.max_novel)
    if rule.min_agree <= 0 or rule.window <= 0 or not n:
        return ok
    agree = np.zeros(n, dtype=np.int64)
    for d in range(1, rule.window + 1):
        if d >= n:
            break
        limit = rule.max_rate * d + 1
        # neighbour ahead: frame i + d against frame i
        step = img[d:] - img[:-d]
        same = (seq[d:] == seq[:-d]) & (seq[:-d] >= 0) & (step >= 0) & (step <= limit)
        agree[:-d] += same
        agree[d:] += same  # the same pair seen from the later frame (the step is mirrored)
    return ok & (agree >= rule.min_agree)
