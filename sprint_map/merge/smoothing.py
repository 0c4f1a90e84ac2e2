"""The after-drive pipeline: a localised drive's smoothed decisions, ready for the merge rule.

Once a drive has been seen whole, its recorded retrieval hits are decided again from the
smoothed posterior (:meth:`Localizer.smooth_pass <sprint_map.localize.localizer.Localizer.smooth_pass>`),
in up to six steps (``docs/hmm.md``, "Decision: place mass and novelty"):

1. the **smoothed pass** over each frame's ``k`` nearest hits;
2. the **calibrated unmapped place**: the drive's consistent matches give its match distances,
   whose ``novelty_quantile`` quantile within ``novelty_window`` frames becomes each frame's
   unmapped-place distance, and a second pass gives every decision its ``novel_prob``;
3. **verification** on the thumbnails (:mod:`sprint_map.merge.verification`), with them;
4. the **deep pass** over all ``smooth_k`` hits, when deeper than ``k``: frames the rule does not
   accept take its place, marked ``confirmed=False`` (answered, never merged);
5. with GNSS fixes, decisions whose fix-to-place offset breaks their run's
   (:meth:`GnssAid.off_track <sprint_map.localize.gnss.GnssAid.off_track>`) are marked
   ``confirmed=False``;
6. every decision is **settled** by the one rule for what an answer is
   (:meth:`FrameDecision.settled <sprint_map.localize.localizer.FrameDecision.settled>`): a
   match whose calibrated ``novel_prob`` is at least its ``prob`` (or whose ``prob`` is below
   ``min_confidence``) answers "no match", as the causal filter answers such a frame.

:func:`smoothed_decisions` is the one entry: ``ingest``, ``localize --smooth``, ``eval``, the
service's commit and the ingest farm all call it.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from typing import Protocol

import numpy as np

from sprint_map.errors import UnknownSequenceError
from sprint_map.localize.localizer import FrameDecision, Localizer, nearest_hit
from sprint_map.merge.rule import CALIBRATE_MIN_FRAMES, MergeRule, select_merges
from sprint_map.util.arrays import DescriptorsLike
from sprint_map.util.validation import validate_descriptors

__all__ = ["CALIBRATE_MIN_RUN", "MergeableMap", "MergeSettings", "local_quantiles",
           "smoothed_decisions"]

#: Shortest run (frames) of the matches a drive's unmapped place is calibrated on: the merge
#: rule's runs without its lookalike tests.
CALIBRATE_MIN_RUN = 5

Hits = list[tuple[np.ndarray, np.ndarray]]


class MergeSettings(Protocol):
    """What the pipeline reads of a map's config (:class:`sprint_map.config.MapConfig` is one)."""

    @property
    def dim(self) -> int: ...

    @property
    def merge(self) -> MergeRule: ...


class MergeableMap(Protocol):
    """A map whose drives can be smoothed for merging (:class:`sprint_map.map.SprintMap` is
    one): its config and its frames' thumbnails."""

    @property
    def config(self) -> MergeSettings: ...

    def thumbnail(self, seq_id: int, image_id: int) -> bytes | None: ...


def smoothed_decisions(localizer: Localizer, smap: MergeableMap,
                       descriptors: DescriptorsLike | None = None,
                       thumbnails: Sequence[bytes] | None = None) -> list[FrameDecision]:
    """The decisions of every frame ``localizer`` has seen, re-made for merging (steps 1-4
    above). ``localizer`` must have been made with ``record=True``; its causal decisions are
    unchanged. ``descriptors`` (the drive's rows) let the deep pass search them ``smooth_k``
    deep now where fewer hits were recorded (``record_k``: the service). ``thumbnails``, one
    JPEG per frame, turn verification on.

    Notes
    -----
    Two filter and backward steps per frame (three with ``smooth_k``), all O(live); memory
    O(live) per frame. Verification adds one keypoint matching per
    :data:`~sprint_map.merge.verification.SAMPLE_EVERY` frames of the refused runs.
    """
    if localizer.is_empty:
        return [FrameDecision(i, None, None, 0.0, novel_prob=1.0)
                for i in range(localizer.frames_seen)]
    if not localizer.record:
        raise ValueError("smoothed decisions need a Localizer made with record=True")
    start = time.perf_counter()
    cfg = localizer.config
    with localizer.pinned() as changed:
        if changed:  # a writer committed since the hits were searched: the components are
            # re-read (the cache was cleared), hits on sequences removed meanwhile dropped
            localizer.hits = [(np.where(localizer.source.visible(ids), ids, -1), dists)
                              for ids, dists in localizer.hits]
        deep_hits = _deep_hits(localizer, smap, descriptors)
        deep = cfg.smooth_k > cfg.k and any(len(ids) > cfg.k for ids, _ in deep_hits)
        # the k nearest (as the causal filter reads them): the model the rule is tuned on
        hits = ([(ids[:cfg.k], dists[:cfg.k]) for ids, dists in localizer.hits] if deep
                else localizer.hits)
        out = _with_nearest(localizer.smooth_pass(hits), localizer.hits)
        novelty = calibrated_novelty(out, localizer, smap.config.merge)
        if novelty is not None:
            calibrated = localizer.smooth_pass(hits, novelty)
            out = [dataclasses.replace(d, novel_prob=c.novel_prob)
                   for d, c in zip(out, calibrated, strict=True)]
        if thumbnails is not None:
            out = _verify(out, thumbnails, smap)
        if deep:
            out = _deep_decisions(localizer, smap.config.merge, out, deep_hits)
        if localizer.gnss is not None:  # a place stuck while the fixes move on
            stuck = localizer.gnss.off_track(
                np.array([d.frame for d in out]),
                np.array([-1 if d.vertex_id is None else d.vertex_id for d in out]))
            out = [dataclasses.replace(d, confirmed=False) if x else d
                   for d, x in zip(out, stuck.tolist(), strict=True)]
        # One rule for what an answer is: a frame the calibrated unmapped place claims is
        # "no match", as the causal filter would answer it (never merged either way).
        out = [d.settled(cfg.min_confidence) for d in out]
    localizer.timing.smooth_ms = (time.perf_counter() - start) * 1e3
    return out


def _with_nearest(decisions: list[FrameDecision], hits: Hits) -> list[FrameDecision]:
    """``decisions`` with each frame's best hit (distance and vertex) over all its recorded
    hits (the pass may have read only the ``k`` nearest, whose best is the same)."""
    out = []
    for d, h in zip(decisions, hits, strict=True):
        distance, nearest = nearest_hit(*h)
        same = d.distance == distance and d.nearest == nearest
        out.append(d if same else dataclasses.replace(d, distance=distance, nearest=nearest))
    return out


def calibrated_novelty(decisions: list[FrameDecision], localizer: Localizer,
                       rule: MergeRule) -> np.ndarray | None:
    """Per-frame unmapped-place distance for this drive (``inf``: none at that frame), or None
    to keep the config's: calibration off, set by hand, or too few matched frames.

    It is calibrated on the drive's consistent matches: the merge rule's frames without its
    contrast gate, in runs of at least :data:`CALIBRATE_MIN_RUN` frames.

    Notes
    -----
    O(n w log w) for ``w = 2 * novelty_window + 1`` (:func:`local_quantiles`).
    """
    cfg = localizer.config
    if not cfg.novelty_quantile or cfg.novelty_dist is not None:
        return None
    relaxed = dataclasses.replace(rule, max_contrast=0.0,
                                  min_run=min(rule.min_run, CALIBRATE_MIN_RUN))
    matched = select_merges(decisions, relaxed)
    if int(matched.sum()) < CALIBRATE_MIN_FRAMES:
        return None
    return local_quantiles(np.array([d.distance for d in decisions]), matched,
                           cfg.novelty_quantile, cfg.novelty_window, CALIBRATE_MIN_FRAMES)


def _deep_hits(localizer: Localizer, smap: MergeableMap,
               descriptors: DescriptorsLike | None) -> Hits:
    """The hits of the deep pass: the recorded ones, or, where they are shallower than
    ``smooth_k`` and the drive's ``descriptors`` are given, a search of them now (one batch;
    the map is pinned by the caller)."""
    deep_k = localizer.config.smooth_k
    hits = localizer.hits
    if (descriptors is None or deep_k <= localizer.config.k or not hits
            or all(len(ids) >= deep_k for ids, _ in hits)):
        return hits
    rows = validate_descriptors(np.asarray(descriptors), smap.config.dim)
    if len(rows) != len(hits):
        raise ValueError(f"smoothed decisions got {len(rows)} descriptors for {len(hits)} "
                         "localised frames")
    dists, ids = localizer.source.search(rows, deep_k)
    return list(zip(ids, dists, strict=True))


def _deep_decisions(localizer: Localizer, rule: MergeRule, shallow: list[FrameDecision],
                    deep_hits: Hits) -> list[FrameDecision]:
    """Step 4: each frame the merge rule accepts in ``shallow`` keeps that acceptance (reported
    at the deep place when that lies on the same sequence within ``place_radius`` images);
    every other frame takes the deep pass's decision, marked ``confirmed=False``.
    ``novel_prob`` is always the calibrated one of ``shallow``.

    Notes
    -----
    One more filter step and backward step per frame, over ``smooth_k`` hits.
    """
    accepted = select_merges(shallow, rule)
    deep = _with_nearest(localizer.smooth_pass(deep_hits), localizer.hits)
    radius = localizer.config.place_radius
    out = []
    for s, d, ok in zip(shallow, deep, accepted.tolist(), strict=True):
        if not ok:
            out.append(dataclasses.replace(d, novel_prob=s.novel_prob, confirmed=False))
        elif (d.seq_id == s.seq_id and d.image_id is not None and s.image_id is not None
                and abs(d.image_id - s.image_id) <= radius):
            out.append(dataclasses.replace(d, novel_prob=s.novel_prob, contrast=s.contrast,
                                           verified=s.verified))
        else:
            out.append(s)
    return out


def _verify(decisions: list[FrameDecision], thumbnails: Sequence[bytes], smap: MergeableMap
            ) -> list[FrameDecision]:
    """Step 3: ``verified`` set on the frames of the runs that the merge rule refuses only for
    its lookalike tests and that the map's thumbnails confirm; then ``confirmed`` cleared on
    the accepted frames of runs that the drive's own images deny a revisit to, outside their
    verified stretches (:meth:`RunVerifier.contradicted
    <sprint_map.merge.verification.RunVerifier.contradicted>`). Unchanged when verification is
    off or the thumbnails are not one per frame (the commit refuses those)."""
    from sprint_map.merge.verification import RunVerifier

    config = smap.config
    if not config.merge.verify_inliers or len(thumbnails) != len(decisions):
        return decisions

    def map_thumbnail(seq_id: int, image_id: int) -> bytes | None:
        try:  # None: the frame keeps none, or its drive was removed since the search
            return smap.thumbnail(seq_id, image_id)
        except UnknownSequenceError:
            return None

    rule = config.merge
    gap = max(rule.window, 1)
    verifier = RunVerifier(thumbnails, map_thumbnail, config.merge.verify_inliers, rule.min_run)
    relaxed = dataclasses.replace(rule, max_contrast=0.0, max_novel=1.0)
    candidates = select_merges(decisions, relaxed)
    accepted = select_merges(decisions, rule)
    if (candidates & ~accepted).any():
        verified = verifier.verified(decisions, candidates, gap, rule.max_rate, skip=accepted)
        decisions = [dataclasses.replace(d, verified=True) if v else d
                     for d, v in zip(decisions, verified.tolist(), strict=True)]
        accepted = select_merges(decisions, rule)
    denied = verifier.contradicted(decisions, accepted, gap, rule.max_rate)
    return [dataclasses.replace(d, confirmed=False) if x else d
            for d, x in zip(decisions, denied.tolist(), strict=True)]


def local_quantiles(values: np.ndarray, mask: np.ndarray, q: float, window: int,
                    min_count: int) -> np.ndarray:
    """For every frame, the ``q`` quantile of ``values[mask]`` over the frames within
    ``window`` of it (0: the whole sequence), or over the whole sequence where fewer than
    ``min_count`` masked frames lie that close.

    Notes
    -----
    O(n w log w) for ``w = 2 * window + 1``.
    """
    n = len(values)
    overall = float(np.quantile(values[mask], q))
    out = np.full(n, overall)
    if window <= 0:
        return out
    idx = np.flatnonzero(mask)
    lo = np.searchsorted(idx, np.arange(n) - window)
    hi = np.searchsorted(idx, np.arange(n) + window, side="right")
    for t in range(n):
        if hi[t] - lo[t] >= min_count:
            out[t] = float(np.quantile(values[idx[lo[t]:hi[t]]], q))
    return out
