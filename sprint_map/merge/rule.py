"""The merge rule: which localisation decisions of a drive become permanent edges.

A merged edge is permanent and carries belief for every later drive, so the rule is tuned for
precision (``docs/architecture.md``, "Lifelong merge"). A decision on frame ``i`` matched to
``(s, j)`` is merged when all of these hold:

1. it is confident: its place probability is at least ``merge_threshold``;
2. it is not novel: its probability of being an unmapped place (``novel_prob``) is at most
   ``merge_max_novel``;
3. it is as close to the map as this drive's matches are: its frame's best-hit distance is
   at most the ``merge_dist_quantile`` quantile of the best-hit distances of the frames that
   pass every other test (calibrated per drive: under rain or at night every distance to the
   map grows, and the drive's own accepted matches say by how much). A lookalike street
   (perceptual aliasing) is matched, but less closely than the streets the drive really
   shares with the map;
4. it lies on a long enough run: at least ``merge_min_run`` frames passing 1-3, matched one
   after the other along the same sequence, each at most ``merge_window`` frames after the
   previous one of the run and at an image ``0 <= step <= merge_max_rate * gap + 1`` ahead
   of it. A mapped road is followed for as long as the drive stays on it; a lookalike stretch
   ends where the streets differ and the match jumps elsewhere. Around each frame, the run's
   images must also advance by at least ``merge_min_advance`` per frame: a match stuck on one
   image while the drive goes on is a belief coasting on a place the drive has left (a
   tunnel, a dark or featureless stretch);
5. its run stands out from the rest of the map: the median ``contrast`` of the run's frames
   (the frame's best hit inside the decided place over its best hit anywhere else in the map,
   :func:`sprint_map.hmm.decision.place_contrast`) is at most ``merge_max_contrast``. A
   lookalike street is lined up frame after frame by the sequence model, but along it
   something elsewhere in the map keeps looking as much like the drive as the place it is
   matched to; along a street the map really holds, the matched place is the closest thing
   to most frames. Frames without a contrast (causal decisions) do not count in the median;
   a run with none passes;
6. optionally (``merge_min_agree`` > 0), at least that many of the ``merge_window`` frames on
   either side agree with it in the sense of 4;
7. it is not on the contested images of a *teleport*: two runs of the drive on one sequence,
   the later one re-entering images of the earlier one sooner than a drive can come back to a
   place it has just passed (:func:`teleports`). On the images both runs claim, at most one of
   them is right and nothing in the images tells which (a copied street verifies as well as
   the street it copies), so neither is merged there; what is left of either run is merged
   only if it is still a run of ``merge_min_run`` frames.

A decision marked ``verified`` (its run confirmed on the thumbnails by geometric
verification, :mod:`sprint_map.merge.verification`) is merged even if tests 1-3 and 5 refused it
(test 7 still applies):
many keypoints that fit one two-view geometry say "the same place" more surely than a
lookalike test can say "a lookalike".

A decision marked ``confirmed=False`` (the deeper pass of a drive searched with ``smooth_k``
neighbours, where the rule did not accept the ``k``-neighbour decision; or a run claiming a
revisit that the drive's own thumbnails deny, :meth:`RunVerifier.contradicted
<sprint_map.merge.verification.RunVerifier.contradicted>`; or one whose place lies beyond the
gate of its frame's GNSS fix, :mod:`sprint_map.localize.gnss`) is never merged.

The decisions are usually the smoothed ones (:mod:`sprint_map.hmm.smoother`): after the whole
drive has been seen, the future of the drive supports or contradicts each frame.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, fields
from typing import Any, Protocol

import numpy as np

from sprint_map.util.dataclass_dict import check_int

__all__ = ["MergeDecision", "MergeRule", "run_ids", "run_lengths", "run_members",
           "select_merges", "teleports"]

#: Frames that must pass the other tests before the distance test is calibrated on them.
CALIBRATE_MIN_FRAMES = 10


class MergeDecision(Protocol):
    """What the rule reads of a decision (:class:`sprint_map.localize.localizer.FrameDecision`)."""

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
    @property
    def distance(self) -> float: ...
    @property
    def contrast(self) -> float: ...
    @property
    def confirmed(self) -> bool: ...

    @property
    def verified(self) -> bool: ...


@dataclass(frozen=True)
class MergeRule:
    """Which decisions of a drive become edges: the rule's parameters (``MapConfig.merge``);
    the module docstring says what each test does. ValueError for a value out of range."""

    #: Minimum place probability of a merged decision.
    threshold: float = 0.5
    #: A decision more likely than this to be an unmapped place is not merged.
    max_novel: float = 0.2
    #: Largest frame gap between consecutive frames of a run (and the agreement window).
    window: int = 3
    #: Neighbours within ``window`` that must agree along the same sequence (0: off).
    min_agree: int = 0
    #: Images of the matched sequence a run may advance per frame.
    max_rate: float = 3.0
    #: Frames of the shortest merged run (0 or 1: off).
    min_run: int = 20
    #: A merged frame is at most this quantile of the drive's accepted best-hit distances (0: off).
    dist_quantile: float = 0.0
    #: Images per frame a run advances, at least, around each frame.
    min_advance: float = 0.3
    #: Largest median contrast of a merged run (0: off).
    max_contrast: float = 0.95
    #: Median inliers for geometric verification on thumbnails to confirm a stretch (0: off).
    verify_inliers: int = 35
    #: Store each merge edge in both directions (query -> map and map -> query).
    both_ways: bool = True

    def __post_init__(self) -> None:
        if not 0 <= self.threshold <= 1:
            raise ValueError("threshold must be in [0, 1]")
        if not 0 <= self.max_novel <= 1:
            raise ValueError("max_novel must be in [0, 1]")
        check_int("window", self.window, 0)
        if not isinstance(self.min_agree, int) or not 0 <= self.min_agree <= 2 * self.window:
            raise ValueError("min_agree must be an integer in [0, 2 * window]")
        if not self.max_rate > 0:
            raise ValueError("max_rate must be > 0")
        check_int("min_run", self.min_run, 0)
        if not 0 <= self.dist_quantile <= 1:
            raise ValueError("dist_quantile must be in [0, 1]")
        if not 0 <= self.min_advance <= self.max_rate:
            raise ValueError("min_advance must be in [0, max_rate]")
        if not 0 <= self.max_contrast < math.inf:
            raise ValueError("max_contrast must be a finite number >= 0")
        check_int("verify_inliers", self.verify_inliers, 0)

    @classmethod
    def permissive(cls, **changes: Any) -> MergeRule:
        """Every test off but the probability threshold (a baseline for experiments and
        tests), with ``changes``: ``MergeRule.permissive(min_run=5)`` tests runs alone."""
        base = {"max_novel": 1.0, "window": 0, "min_run": 0, "min_advance": 0.0,
                "max_contrast": 0.0, "verify_inliers": 0}
        return cls(**{**base, **changes})

    def reported(self) -> dict[str, float | bool]:
        """The rule as ``results.json``'s ``merge_rule`` reports it (``merge_``-prefixed)."""
        return {f"merge_{f.name}": getattr(self, f.name) for f in fields(self)}


def select_merges(decisions: Sequence[MergeDecision], rule: MergeRule) -> np.ndarray:
    """Which decisions the rule merges: a boolean array, one entry per decision.

    ``decisions`` must be the consecutive frames of one drive, in order (``frame`` is
    ``0 .. n-1``).

    Notes
    -----
    O(n * merge_window).

    Examples
    --------
    >>> from sprint_map.localize.localizer import FrameDecision
    >>> ds = [FrameDecision(i, 0, 10 + i, 0.9) for i in range(5)]
    >>> select_merges(ds, MergeRule.permissive(window=2, min_agree=1)).tolist()
    [True, True, True, True, True]
    >>> ds[2] = FrameDecision(2, 1, 40, 0.9)  # a jump to another drive: no neighbour agrees
    >>> select_merges(ds, MergeRule.permissive(window=2, min_agree=1)).tolist()
    [True, True, False, True, True]
    >>> select_merges(ds, MergeRule.permissive(window=2, min_run=3)).tolist()
    [True, True, False, True, True]
    >>> select_merges(ds, MergeRule.permissive(window=2, min_run=5)).tolist()
    [False, False, False, False, False]
    """
    n = len(decisions)
    seq = np.array([-1 if d.seq_id is None else d.seq_id for d in decisions], dtype=np.int64)
    img = np.array([-1 if d.image_id is None else d.image_id for d in decisions], dtype=np.int64)
    prob = np.array([d.prob for d in decisions], dtype=np.float64)
    novel = np.array([d.novel_prob for d in decisions], dtype=np.float64)
    confirmed = np.array([d.confirmed for d in decisions], dtype=bool)
    ok = (seq >= 0) & (prob >= rule.threshold) & (novel <= rule.max_novel) & confirmed
    gap = max(rule.window, 1)

    def on_runs(keep: np.ndarray) -> np.ndarray:
        if rule.min_run <= 1:
            return keep
        return keep & (run_lengths(np.where(keep, seq, -1), img, gap, rule.max_rate,
                                   rule.min_advance) >= rule.min_run)

    accepted = on_runs(ok)
    if rule.max_contrast > 0 and accepted.any():
        contrast = np.array([d.contrast for d in decisions], dtype=np.float64)
        ok &= ~_low_contrast_runs(np.where(accepted, seq, -1), img, contrast, gap,
                                  rule.max_rate, rule.max_contrast)
        accepted = on_runs(ok)
    if rule.dist_quantile > 0 and int(accepted.sum()) >= CALIBRATE_MIN_FRAMES:
        dist = np.array([d.distance for d in decisions], dtype=np.float64)
        limit = float(np.quantile(dist[accepted], rule.dist_quantile))
        accepted = on_runs(ok & (dist <= limit))
    verified = np.array([d.verified for d in decisions], dtype=bool) & confirmed & (seq >= 0)
    if rule.min_agree <= 0 or rule.window <= 0 or not n:
        return _without_teleports(accepted | verified, seq, img, gap, rule)
    agree = np.zeros(n, dtype=np.int64)
    for d in range(1, rule.window + 1):
        if d >= n:
            break
        limit_step = rule.max_rate * d + 1
        # neighbour ahead: frame i + d against frame i
        step = img[d:] - img[:-d]
        same = (seq[d:] == seq[:-d]) & (seq[:-d] >= 0) & (step >= 0) & (step <= limit_step)
        agree[:-d] += same
        agree[d:] += same  # the same pair seen from the later frame (the step is mirrored)
    return _without_teleports((accepted & (agree >= rule.min_agree)) | verified, seq, img, gap,
                              rule)


def _without_teleports(merged: np.ndarray, seq: np.ndarray, img: np.ndarray, gap: int,
                       rule: MergeRule) -> np.ndarray:
    """``merged`` less the contested frames of teleports (test 7), and less what is left of a
    run that lost some of them if it is no longer a run of ``min_run`` frames. O(n * gap)."""
    contested = teleports(np.where(merged, seq, -1), img, gap, rule.max_rate)
    if not contested.any():
        return merged
    run = run_ids(np.where(merged, seq, -1), img, gap, rule.max_rate)
    touched = np.isin(run, np.unique(run[contested])) & (run >= 0)
    left = merged & ~contested
    short = run_lengths(np.where(left, seq, -1), img, gap, rule.max_rate) < max(rule.min_run, 1)
    out: np.ndarray = left & ~(touched & short)
    return out


def teleports(seq: np.ndarray, img: np.ndarray, max_gap: int, max_rate: float) -> np.ndarray:
    """The contested frames of teleports: a boolean mask over the frames.

    Two runs on one sequence that share images, the second coming to them ``gap`` frames after
    the first left them (``gap > 0``), claim the drive came back. A second run that re-enters
    more than ``max_rate * (gap + max_gap)`` shared images came back sooner than a drive can
    (it must leave and return facing the same way): a street and its copy driven one after the
    other, or a lookalike of a stretch just driven. The frames of either run on the images both
    claim are contested.

    Notes
    -----
    O(n * max_gap) for the runs, plus O(R^2) for R runs.

    Examples
    --------
    >>> seq = np.zeros(8, dtype=np.int64)
    >>> img = np.array([6, 8, 10, 12, 14, 10, 12, 14])  # back to image 10 at once
    >>> teleports(seq, img, 1, 1.0).tolist()
    [False, False, True, True, True, True, True, True]
    >>> seq = np.r_[[0] * 4, [-1] * 12, [0] * 4]  # back to image 10 after 12 frames elsewhere
    >>> img = np.r_[[10, 11, 12, 13], [-1] * 12, [10, 11, 12, 13]]
    >>> bool(teleports(seq, img, 1, 1.0).any())
    False
    """
    runs = list(run_members(run_ids(seq, img, max_gap, max_rate)))
    out = np.zeros(len(seq), dtype=bool)
    for a, first in enumerate(runs):
        for second in runs[a + 1:]:
            if seq[first[0]] != seq[second[0]]:
                continue
            lo = max(int(img[first].min()), int(img[second].min()))
            hi = min(int(img[first].max()), int(img[second].max()))
            if hi < lo:
                continue
            on_a = first[(img[first] >= lo) & (img[first] <= hi)]
            on_b = second[(img[second] >= lo) & (img[second] <= hi)]
            if not on_a.size or not on_b.size:
                # One run stepped over the shared images (a step of a run spans at most
                # max_rate * max_gap + 1 images): none of its frames lies on them to contest.
                continue
            # frames between leaving the shared images and coming back to them
            gap = int(max(on_b[0] - on_a[-1], on_a[0] - on_b[-1]))
            if gap > 0 and hi - lo + 1 > max_rate * (gap + max_gap):
                out[on_a] = out[on_b] = True
    return out


def run_lengths(seq: np.ndarray, img: np.ndarray, max_gap: int, max_rate: float,
                min_advance: float = 0.0) -> np.ndarray:
    """For every frame, the number of matched frames in its run (0 for "no match").

    A run is a chain of matched frames on one sequence, each at most ``max_gap`` frames after
    the previous one of the chain and at an image ``0 <= step <= max_rate * gap + 1`` ahead of
    it. Each matched frame continues the run of the latest matched frame it fits (so an
    outlier decision between two frames of a run neither breaks the run nor joins it).

    Where a run's images advance by less than ``min_advance`` per frame (over the run's frames
    within ``5 * max_gap`` frames of a member, first to last), that member counts as 0: a drive
    moving along a mapped road is matched to images that move too, while a match stuck on one
    image as the drive goes on is a belief coasting on a place the drive has left.

    Notes
    -----
    O(n * max_gap).
    """
    n = len(seq)
    run = run_ids(seq, img, max_gap, max_rate)
    n_runs = int(run.max()) + 1 if n else 0
    held = run >= 0
    sizes = np.bincount(run[held], minlength=n_runs)
    out = np.zeros(n, dtype=np.int64)
    out[held] = sizes[run[held]]
    if min_advance > 0 and n_runs:
        out[held & ~_advancing(run, img, min_advance, max(max_gap, 1) * 5)] = 0
    return out


def run_ids(seq: np.ndarray, img: np.ndarray, max_gap: int, max_rate: float) -> np.ndarray:
    """The run (see :func:`run_lengths`) of every frame: 0, 1, ... in order of their first
    frame; -1 for "no match". O(n * max_gap)."""
    n = len(seq)
    run = np.full(n, -1, dtype=np.int64)
    n_runs = 0
    for f in range(n):
        if seq[f] < 0:
            continue
        for g in range(f - 1, max(f - max_gap, 0) - 1, -1):
            if seq[g] == seq[f] and run[g] >= 0 and 0 <= img[f] - img[g] <= max_rate * (f - g) + 1:
                run[f] = run[g]
                break
        else:
            run[f] = n_runs
            n_runs += 1
    return run


def run_members(run: np.ndarray) -> Iterator[np.ndarray]:
    """The frames of each run (``run`` as :func:`run_ids` gives it), ascending, run by run.
    O(n log n)."""
    held = np.flatnonzero(run >= 0)
    if not held.size:
        return
    by_run = held[np.argsort(run[held], kind="stable")]
    starts = np.flatnonzero(np.r_[True, run[by_run[1:]] != run[by_run[:-1]]])
    for a, b in zip(starts.tolist(), np.r_[starts[1:], by_run.size].tolist(), strict=True):
        yield by_run[a:b]


def _low_contrast_runs(seq: np.ndarray, img: np.ndarray, contrast: np.ndarray, max_gap: int,
                       max_rate: float, limit: float) -> np.ndarray:
    """The frames of the runs (see :func:`run_ids`) whose median contrast (NaN ignored)
    exceeds ``limit``. O(n * max_gap)."""
    out = np.zeros(len(seq), dtype=bool)
    for frames in run_members(run_ids(seq, img, max_gap, max_rate)):
        values = contrast[frames]
        values = values[~np.isnan(values)]
        if values.size and float(np.median(values)) > limit:
            out[frames] = True
    return out


def _advancing(run: np.ndarray, img: np.ndarray, min_advance: float, half: int) -> np.ndarray:
    """Whether each run member's images advance by ``min_advance`` per frame over the run's
    frames within ``half`` frames of it (first to last of them): a run that stalls for a
    stretch loses that stretch, even if the run as a whole moves on."""
    ok = np.zeros(len(run), dtype=bool)
    for frames in run_members(run):
        lo = np.searchsorted(frames, frames - half)
        hi = np.searchsorted(frames, frames + half, side="right") - 1
        span = frames[hi] - frames[lo]
        moved = img[frames[hi]] - img[frames[lo]]
        ok[frames] = (span == 0) | (moved >= min_advance * span)
    return ok
