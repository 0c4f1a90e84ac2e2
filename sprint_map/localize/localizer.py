"""Localising a query sequence against a map.

Per frame: k-NN retrieval over the whole map (FAISS) gives the observations; the SPRINT filter
updates the belief over the active set only; the most probable place is the decision. The
:class:`Localizer` serves both a vehicle streaming frames one at a time (:meth:`Localizer.step`)
and offline localisation of a whole sequence (:meth:`Localizer.localize`, which batches its
k-NN searches: one search of B queries is much cheaper than B searches of one).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from sprint_map.config import MapConfig
from sprint_map.errors import UnknownSequenceError
from sprint_map.hmm.cache import ComponentCache
from sprint_map.hmm.config import HMMConfig
from sprint_map.hmm.decision import Decision
from sprint_map.hmm.graph import GraphSource
from sprint_map.hmm.smoother import ForwardBackward
from sprint_map.hmm.sprint_filter import SprintFilter
from sprint_map.merge.rule import CALIBRATE_MIN_FRAMES, select_merges
from sprint_map.util.arrays import DescriptorsLike, SearchResult
from sprint_map.util.validation import validate_descriptors

__all__ = ["CALIBRATE_MIN_RUN", "SEARCH_BATCH", "FrameDecision", "LocalizableMap", "Localizer",
           "MapView", "Timing", "local_quantiles", "recorded_k"]

#: Query rows per batched k-NN search in :meth:`Localizer.localize`.
SEARCH_BATCH = 256

#: Shortest run (frames) of the matches a drive's unmapped place is calibrated on
#: (:meth:`Localizer.smoothed`): the merge rule's runs without its lookalike tests.
CALIBRATE_MIN_RUN = 5


class MapView(GraphSource, Protocol):
    """What a :class:`Localizer` reads of a map, through a view of its own
    (:class:`sprint_map.localize.map_graph.MapGraphSource` is one).

    Besides the HMM's :class:`~sprint_map.hmm.graph.GraphSource` (components of vertices, a
    component's arrays): k-NN search, vertex -> ``(seq_id, image_id)``, the vertex count and
    which vertices are live, all read from one pinned snapshot during a ``localize``.
    """

    @property
    def vertices(self) -> int: ...

    def pinned(self) -> AbstractContextManager[bool]: ...

    def mark_current(self) -> None: ...

    def visible(self, vertex_ids: np.ndarray) -> np.ndarray: ...

    def search(self, queries: DescriptorsLike, k: int) -> SearchResult: ...

    def locate(self, vertex_ids: Any) -> list[tuple[int, int]]: ...


class LocalizableMap(Protocol):
    """A map a :class:`Localizer` can read (:class:`sprint_map.map.SprintMap` is one): its
    config and a new :class:`MapView` for each localizer."""

    @property
    def config(self) -> MapConfig: ...

    def view(self) -> MapView: ...

    def thumbnail(self, seq_id: int, image_id: int) -> bytes | None: ...


@dataclass(frozen=True)
class FrameDecision:
    """The answer for one query frame; ``seq_id``/``image_id`` are None for "no match".

    ``prob`` is the posterior mass of the decided place (the vertex, its temporal neighbours and
    the vertices joined to them by edges); for "no match" it is that of the best candidate,
    which ``best`` still names (``(seq_id, image_id)``, None when the map is empty).
    ``novel_prob`` is the posterior probability that the frame shows a place the map does not
    hold (the filter's "unmapped place" state; 1 when the map is empty). ``distance`` is the
    frame's best retrieval hit's squared-L2 distance (inf when nothing was retrieved), which
    the merge rule compares with the drive's accepted matches. ``contrast`` (smoothed matches
    only, NaN otherwise) is the best hit inside the decided place over the best hit elsewhere
    in the map (:func:`sprint_map.hmm.decision.place_contrast`): below 1 the place stands out,
    at 1 or more a lookalike is as close; the merge rule reads it along runs. ``confirmed``
    is False for a smoothed decision the merge rule may not merge: one of the deeper pass of
    a drive searched with ``smooth_k`` neighbours where the ``k``-neighbour model's decision
    was not accepted (:meth:`Localizer.smoothed`), or one on a run that claims a revisit the
    drive's own thumbnails deny, outside its verified stretches
    (:meth:`sprint_map.merge.verification.RunVerifier.contradicted`). ``verified`` is True for a smoothed
    decision on a run that geometric verification on the thumbnails confirmed
    (:mod:`sprint_map.merge.verification`): the merge rule merges it even if a lookalike test
    refused it.
    """

    frame: int
    seq_id: int | None
    image_id: int | None
    prob: float
    vertex_id: int | None = None
    best: tuple[int, int] | None = None
    novel_prob: float = 0.0
    distance: float = math.inf
    contrast: float = math.nan
    confirmed: bool = True
    verified: bool = False

    @property
    def is_match(self) -> bool:
        return self.seq_id is not None

    def to_dict(self) -> dict[str, Any]:
        return {"frame": self.frame, "seq_id": self.seq_id, "image_id": self.image_id,
                "prob": round(float(self.prob), 6), "novel_prob": round(float(self.novel_prob), 6),
                "distance": round(self.distance, 6) if math.isfinite(self.distance) else None,
                "contrast": round(self.contrast, 6) if math.isfinite(self.contrast) else None,
                "confirmed": self.confirmed, "verified": self.verified}


@dataclass
class Timing:
    """Per-frame timing, retrieval and HMM apart, and the active-set size after each frame.

    In batch localisation one search serves many frames; each frame is charged an equal share.
    """

    retrieval_ms: list[float] = field(default_factory=list)
    hmm_ms: list[float] = field(default_factory=list)
    active_vertices: list[int] = field(default_factory=list)
    active_components: list[int] = field(default_factory=list)
    #: Time of the last smoothing pass (forward again + backward + decisions), whole drive.
    smooth_ms: float = 0.0

    @property
    def frames(self) -> int:
        return len(self.hmm_ms)

    def to_dict(self) -> dict[str, Any]:
        n = max(self.frames, 1)
        ret = np.asarray(self.retrieval_ms or [0.0])
        hmm = np.asarray(self.hmm_ms or [0.0])
        act = np.asarray(self.active_vertices or [0])
        return {
            "frames": self.frames,
            "smooth_ms_per_frame": round(self.smooth_ms / n, 4),
            "retrieval_ms_total": round(float(ret.sum()), 3),
            "hmm_ms_total": round(float(hmm.sum()), 3),
            "retrieval_ms_per_frame": round(float(ret.sum()) / n, 4),
            "hmm_ms_per_frame": round(float(hmm.sum()) / n, 4),
            "retrieval_ms_p50": round(float(np.percentile(ret, 50)), 4),
            "retrieval_ms_p99": round(float(np.percentile(ret, 99)), 4),
            "hmm_ms_p50": round(float(np.percentile(hmm, 50)), 4),
            "hmm_ms_p99": round(float(np.percentile(hmm, 99)), 4),
            "active_vertices_mean": round(float(act.mean()), 1),
            "active_vertices_max": int(act.max()),
        }


class Localizer:
    """Localise one query sequence, frame by frame, against ``smap``.

    Parameters
    ----------
    smap : LocalizableMap
        The map (a :class:`~sprint_map.map.SprintMap`; read-only is enough); its state is read
        through its :meth:`~LocalizableMap.view`, from LMDB snapshots.
    hmm : HMMConfig, optional
        Model parameters; default the map's own (``smap.config.hmm``).
    cache : ComponentCache, optional
        Where loaded components are kept; default a private one of
        ``config.cache_budget_bytes``.

    Notes
    -----
    Per-frame cost: one k-NN search over the map, plus the HMM update in
    O(W * n_active + nnz(U_active)) where ``n_active`` counts the vertices of the active
    components only, plus loading components that join the active set (LRU-cached).
    """

    def __init__(self, smap: LocalizableMap, hmm: HMMConfig | None = None,
                 cache: ComponentCache | None = None, *, record: bool = False,
                 record_k: int | None = None) -> None:
        self.map = smap
        self.config = hmm or smap.config.hmm
        self.source = smap.view()
        # A cache may be shared by localizers over the same map (the server's sessions).
        self.cache = cache if cache is not None else ComponentCache(self.config.cache_budget_bytes)
        self.filter = SprintFilter(self.config, self.source, self.cache)
        self.timing = Timing()
        self._empty = self.source.vertices == 0
        self._frame = 0
        #: Keep every frame's retrieval hits, for :meth:`smoothed` (O(k) per frame).
        self.record = record
        #: Neighbours searched and kept per recorded frame (None: :func:`recorded_k`; the
        #: service keeps ``k`` and has :meth:`smoothed` search the drive deeper at commit).
        self.record_k = record_k
        self.hits: list[tuple[np.ndarray, np.ndarray]] = []
        #: The per-frame unmapped-place distances the last :meth:`smoothed` calibrated.
        self.novelty_dist: np.ndarray | None = None
        #: Called after every frame with ``(decision, hit ids, hit distances)`` (e.g. a
        #: :class:`sprint_map.localize.trace.TraceRecorder`, which reads ``filter`` too); None: nothing.
        self.observer: Callable[[FrameDecision, np.ndarray, np.ndarray], None] | None = None

    def reset(self) -> None:
        """Start a new query sequence."""
        self.filter.reset()
        self.timing = Timing()
        self._frame = 0
        self.hits = []

    def smoothed(self, descriptors: DescriptorsLike | None = None,
                 thumbnails: Sequence[bytes] | None = None) -> list[FrameDecision]:
        """The decisions of every frame so far, re-made from the smoothed posterior.

        Forward-backward over the same sparse active set (:mod:`sprint_map.hmm.smoother`),
        from the hits recorded while localising (construct with ``record=True``): each frame's
        decision then uses the frames after it as well. The causal decisions are unchanged.

        With ``novelty_quantile`` set (the default), each decision's ``novel_prob`` comes from
        a second pass whose unmapped-place hypothesis is calibrated on this drive: the
        consistent matches of the first pass (:meth:`_calibrated_novelty`) give the drive's
        match distances,
        and their ``novelty_quantile`` quantile within ``novelty_window`` frames becomes each
        frame's ``novelty_dist`` (kept in :attr:`novelty_dist`). The places decided stay
        those of the first pass.

        With ``smooth_k`` > ``k`` (the default), these two passes read the ``k`` nearest hits
        of each frame, and a third pass all ``smooth_k``: the merge rule's accepted decisions
        stay those of the ``k``-hit passes, every other frame takes the third pass's place,
        marked ``confirmed=False`` (never merged; see :meth:`_deep_decisions`). The deep hits
        are the recorded ones; where fewer were recorded (``record_k``), the drive's
        ``descriptors``, if given, are searched ``smooth_k`` deep now, in one batch (the
        service answers its vehicles from ``k`` hits and smooths at commit).

        With the drive's ``thumbnails`` (one JPEG per frame) and ``merge_verify_inliers`` set,
        the runs that the merge rule refuses only for its lookalike tests (contrast gate,
        unmapped-place veto) are checked on the images against the map's own thumbnails
        (:mod:`sprint_map.merge.verification`); the frames of verified stretches are marked
        ``verified`` and merged. Nothing is verified for a map frame without a thumbnail.
        Then two accepted runs matched to the same images of one map sequence (the drive
        passed there twice, they claim) are checked on the drive's own thumbnails: where its
        frames at the shared images do not match each other, each run keeps only its verified
        stretches and its other frames are marked ``confirmed=False``.

        Notes
        -----
        Two more filter steps and backward steps per frame (one without calibration), three
        with ``smooth_k``, all O(live); memory O(live) per frame of the sequence. Verification
        adds one keypoint matching per :data:`~sprint_map.merge.verification.SAMPLE_EVERY` frames
        of the refused runs, and a few per pair of accepted runs on shared images.
        """
        if self._empty:
            return [FrameDecision(i, None, None, 0.0, novel_prob=1.0) for i in range(self._frame)]
        if not self.record:
            raise ValueError("smoothed() needs a Localizer made with record=True")
        start = time.perf_counter()
        with self._pinned() as changed:
            if changed:  # a writer committed since the hits were searched: the components are
                # re-read (the cache was cleared), hits on sequences removed meanwhile dropped
                self.hits = [(np.where(self.source.visible(ids), ids, -1), dists)
                             for ids, dists in self.hits]
            nearest = [_nearest(ids, dists) for ids, dists in self.hits]
            k = self.config.k
            deep_hits = self._deep_hits(descriptors)
            deep = self.config.smooth_k > k and any(len(ids) > k for ids, _ in deep_hits)
            # the k nearest (as the causal filter reads them): the model the rule is tuned on
            hits = [(ids[:k], dists[:k]) for ids, dists in self.hits] if deep else self.hits
            out = self._smooth_pass(nearest, hits)
            novelty = self._calibrated_novelty(out)
            if novelty is not None:
                calibrated = self._smooth_pass(nearest, hits, novelty)
                out = [dataclasses.replace(d, novel_prob=c.novel_prob)
                       for d, c in zip(out, calibrated, strict=True)]
            if thumbnails is not None:
                out = self._verify(out, thumbnails)
            if deep:
                out = self._deep_decisions(nearest, out, deep_hits)
        self.timing.smooth_ms = (time.perf_counter() - start) * 1e3
        return out

    def _deep_hits(self, descriptors: DescriptorsLike | None
                   ) -> list[tuple[np.ndarray, np.ndarray]]:
        """The hits of the deep pass: the recorded ones, or, where they are shallower than
        ``smooth_k`` and the drive's ``descriptors`` are given, a search of them now (one
        batch; the map is pinned by the caller)."""
        deep_k = self.config.smooth_k
        if (descriptors is None or deep_k <= self.config.k or not self.hits
                or all(len(ids) >= deep_k for ids, _ in self.hits)):
            return self.hits
        rows = validate_descriptors(np.asarray(descriptors), self.map.config.dim)
        if len(rows) != len(self.hits):
            raise ValueError(f"smoothed() got {len(rows)} descriptors for {len(self.hits)} "
                             "localised frames")
        dists, ids = self.source.search(rows, deep_k)
        return list(zip(ids, dists, strict=True))

    def _deep_decisions(self, nearest: list[float], shallow: list[FrameDecision],
                        deep_hits: list[tuple[np.ndarray, np.ndarray]]
                        ) -> list[FrameDecision]:
        """The decisions of a drive searched deeper than ``k`` (``smooth_k``), from
        ``shallow``, its calibrated decisions over the ``k`` nearest hits of each frame.

        A further pass reads all ``smooth_k`` hits: under a change of conditions they keep
        more of a place's true neighbours, so its places are the more often right. But the
        merge rule and the unmapped place are tuned on the ``k``-hit model: with many hits
        among few vertices, any hypothesis keeps finding hits near it. So each frame the
        merge rule accepts in ``shallow`` keeps that acceptance (it is reported by the deep
        place when that lies on the same sequence within ``place_radius`` images, else as
        it is), and every other frame takes the deep decision, marked ``confirmed=False``:
        it answers where the frame is, it never becomes an edge. ``novel_prob`` is always
        the calibrated one of ``shallow``.

        Notes
        -----
        One more filter step and backward step per frame, over ``smooth_k`` hits.
        """
        accepted = select_merges(shallow, self.map.config.merge_rule)
        deep = self._smooth_pass(nearest, deep_hits)
        radius = self.config.place_radius
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

    def _verify(self, decisions: list[FrameDecision], thumbnails: Sequence[bytes]
                ) -> list[FrameDecision]:
        """``decisions`` checked on the thumbnails (see :meth:`smoothed`): ``verified`` set on
        the frames of the runs that the merge rule refuses only for its lookalike tests and
        that the map's thumbnails confirm; then ``confirmed`` cleared on the accepted frames
        of runs that the drive's own images deny a revisit to, outside their verified
        stretches (:meth:`RunVerifier.contradicted
        <sprint_map.merge.verification.RunVerifier.contradicted>`). Unchanged when verification is
        off or the thumbnails are not one per frame (the commit refuses those)."""
        from sprint_map.merge.verification import RunVerifier

        config = self.map.config
        if not config.merge_verify_inliers or len(thumbnails) != len(decisions):
            return decisions
        rule = config.merge_rule
        gap = max(rule.window, 1)
        verifier = RunVerifier(thumbnails, self._map_thumbnail, config.merge_verify_inliers,
                               rule.min_run)
        relaxed = dataclasses.replace(rule, max_contrast=0.0, max_novel=1.0)
        candidates = select_merges(decisions, relaxed)
        accepted = select_merges(decisions, rule)
        if (candidates & ~accepted).any():
            verified = verifier.verified(decisions, candidates, gap, rule.max_rate,
                                         skip=accepted)
            decisions = [dataclasses.replace(d, verified=True) if v else d
                         for d, v in zip(decisions, verified.tolist(), strict=True)]
            accepted = select_merges(decisions, rule)
        denied = verifier.contradicted(decisions, accepted, gap, rule.max_rate)
        return [dataclasses.replace(d, confirmed=False) if x else d
                for d, x in zip(decisions, denied.tolist(), strict=True)]

    def _map_thumbnail(self, seq_id: int, image_id: int) -> bytes | None:
        """A map frame's thumbnail; None when it keeps none or has no such frame (a drive
        shorter than that, or removed since the hits were searched)."""
        try:
            return self.map.thumbnail(seq_id, image_id)
        except UnknownSequenceError:
            return None

    def _smooth_pass(self, nearest: list[float], hits: list[tuple[np.ndarray, np.ndarray]],
                     novelty: np.ndarray | None = None) -> list[FrameDecision]:
        fb = ForwardBackward(self.config, self.source, self.cache)
        for t, (ids, dists) in enumerate(hits):
            if novelty is not None:
                nd = float(novelty[t])
                fb.set_novelty_dist(nd if math.isfinite(nd) else None)
            fb.forward(ids, dists)
        return [self._frame_decision(i, d, nearest[i]) for i, d in enumerate(fb.decisions())]

    def _calibrated_novelty(self, decisions: list[FrameDecision]) -> np.ndarray | None:
        """Per-frame ``novelty_dist`` for this drive (see :meth:`smoothed`; ``inf``: none at
        that frame), or None to keep the config's: calibration off, set by hand, or too few
        matched frames to calibrate on.

        The frames it learns from are the drive's consistent matches: the merge rule's frames
        without its lookalike tests (``merge_max_contrast`` off, runs of at least
        :data:`CALIBRATE_MIN_RUN` frames instead of ``merge_min_run``). A lookalike lies about
        as far from the map as a true match under the same conditions, so it does not bias
        how far this drive's matches lie; but leaving its tests on left whole stretches of a
        drive under rain or snow without a frame to calibrate on (``docs/benchmarks.md``,
        "Calibrated on consistent matches").
        """
        cfg = self.config
        if not cfg.novelty_quantile or cfg.novelty_dist is not None:
            return None
        rule = self.map.config.merge_rule
        rule = dataclasses.replace(rule, max_contrast=0.0,
                                   min_run=min(rule.min_run, CALIBRATE_MIN_RUN))
        matched = select_merges(decisions, rule)
        if int(matched.sum()) < CALIBRATE_MIN_FRAMES:
            return None
        self.novelty_dist = local_quantiles(np.array([d.distance for d in decisions]), matched,
                                            cfg.novelty_quantile, cfg.novelty_window,
                                            CALIBRATE_MIN_FRAMES)
        return self.novelty_dist
    def invalidate(self, component_ids: Iterable[int] | None = None) -> None:
        """Tell a long-lived localizer that the map changed (another drive was committed).

        ``component_ids`` are the components the commit changed (all if None): the new one and
        every one merged into it. The belief is kept and re-mapped by vertex id (see
        :meth:`SprintFilter.invalidate`); a localizer started on an empty map starts searching.

        Notes
        -----
        O(live) plus reloading the changed components that are active.
        """
        with self.source.pinned():  # re-mapped as of one snapshot, which the next pin compares
            self._empty = self.source.vertices == 0
            self.filter.invalidate(component_ids)
            self.source.mark_current()

    @contextmanager
    def _pinned(self) -> Iterator[bool]:
        """Read one snapshot of the map in the block (:meth:`MapGraphSource.pinned`): a writer
        committing meanwhile is not half seen. A map changed since the last snapshot (by a writer
        nobody told us of through :meth:`invalidate`) is caught up first; yields whether it
        had changed."""
        with self.source.pinned() as changed:
            self._empty = self.source.vertices == 0
            if changed:
                try:
                    self.filter.invalidate(None)
                except ValueError:  # belief on a removed sequence: start afresh from the hits
                    self.filter.reset()
            yield changed

    def step(self, descriptor: DescriptorsLike) -> FrameDecision:
        """Localise one frame (a vehicle streaming its images)."""
        row = validate_descriptors(np.asarray(descriptor).reshape(1, -1), self.map.config.dim)
        with self._pinned():
            if self._empty:
                return self._no_map_decision()
            start = time.perf_counter()
            dists, ids = self.source.search(row, self.search_k)
            return self._update(ids[0], dists[0], (time.perf_counter() - start) * 1e3)

    def step_hits(self, ids: np.ndarray, dists: np.ndarray, retrieval_ms: float = 0.0
                  ) -> FrameDecision:
        """Localise one frame from its retrieval hits, searched by the caller (the service
        searches the frames of many sessions in one batch).

        The map's search answers a query the same alone or in a batch (bit for bit, see
        :func:`sprint_map.util.exact_search.certified_search`), so with the hits of
        ``smap.search(rows, config.k)`` made against the same map state this equals
        :meth:`step` of the row. The caller keeps the map from changing between the search and
        this call (the service's map gate).
        """
        with self._pinned():
            if self._empty:
                return self._no_map_decision()
            return self._update(ids, dists, retrieval_ms)

    def localize(self, descriptors: DescriptorsLike | Iterable[DescriptorsLike]
                 ) -> list[FrameDecision]:
        """Localise a whole sequence (array, or an iterable of row batches), batching searches."""
        return list(self.iter_localize(descriptors))

    def iter_localize(self, descriptors: DescriptorsLike | Iterable[DescriptorsLike]
                      ) -> Iterator[FrameDecision]:
        """Like :meth:`localize`, yielding decisions as batches are searched.

        The whole sequence is localised against one snapshot of the map (see
        :mod:`sprint_map.storage.snapshot`), held until the last decision is yielded.
        """
        batches = (
            (descriptors[i : i + SEARCH_BATCH] for i in range(0, len(descriptors), SEARCH_BATCH))
            if isinstance(descriptors, np.ndarray) else descriptors
        )
        with self._pinned():
            for batch in batches:
                rows = validate_descriptors(batch, self.map.config.dim)
                if self._empty:
                    for _ in range(len(rows)):
                        yield self._no_map_decision()
                    continue
                start = time.perf_counter()
                dists, ids = self.source.search(rows, self.search_k)
                share = (time.perf_counter() - start) * 1e3 / len(rows)
                for i in range(len(rows)):
                    yield self._update(ids[i], dists[i], share)

    @property
    def search_k(self) -> int:
        """Neighbours searched per frame: :func:`recorded_k` when the hits are recorded for
        :meth:`smoothed`, else ``k``. The causal filter reads the ``k`` nearest either way."""
        if not self.record:
            return self.config.k
        return self.record_k if self.record_k is not None else recorded_k(self.config)

    def _update(self, ids: np.ndarray, dists: np.ndarray, retrieval_ms: float) -> FrameDecision:
        start = time.perf_counter()
        k = self.config.k
        # the search returns the nearest first: the causal filter reads the k nearest
        decision = self.filter.step(ids[:k], dists[:k])
        self.timing.hmm_ms.append((time.perf_counter() - start) * 1e3)
        self.timing.retrieval_ms.append(retrieval_ms)
        self.timing.active_vertices.append(int(decision.n_active_vertices))
        self.timing.active_components.append(int(decision.n_active_components))
        if self.record:
            self.hits.append((np.array(ids, copy=True), np.array(dists, copy=True)))
        frame = self._frame
        self._frame += 1
        out = self._frame_decision(frame, decision, _nearest(ids, dists))
        if self.observer is not None:
            self.observer(out, ids, dists)
        return out

    def _frame_decision(self, frame: int, decision: Decision, distance: float
                        ) -> FrameDecision:
        if decision.vertex_id is None or decision.seq_id is None or decision.image_id is None:
            best = None
            if decision.candidate_id is not None:
                best = self.source.locate([decision.candidate_id])[0]
            return FrameDecision(frame, None, None, float(decision.prob), None, best,
                                 float(decision.sink_prob), distance)
        return FrameDecision(frame, int(decision.seq_id), int(decision.image_id),
                             float(decision.prob), int(decision.vertex_id),
                             (int(decision.seq_id), int(decision.image_id)),
                             float(decision.sink_prob), distance, float(decision.contrast))

    def _no_map_decision(self) -> FrameDecision:
        self.timing.retrieval_ms.append(0.0)
        self.timing.hmm_ms.append(0.0)
        frame = self._frame
        self._frame += 1
        out = FrameDecision(frame, None, None, 0.0, novel_prob=1.0)
        if self.observer is not None:
            self.observer(out, np.empty(0, np.int64), np.empty(0, np.float32))
        return out


def recorded_k(config: HMMConfig) -> int:
    """Neighbours to search per frame for a drive whose hits are kept for the smoothed
    decisions: ``max(k, smooth_k)`` (``ingest``, ``localize --smooth``; the service keeps ``k``
    per frame and searches the drive ``smooth_k`` deep when it commits)."""
    return max(config.k, config.smooth_k)


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


def _nearest(ids: np.ndarray, dists: np.ndarray) -> float:
    """A frame's best-hit distance (squared L2; inf without a valid hit)."""
    d = np.asarray(dists, dtype=np.float64).ravel()[np.asarray(ids).ravel() >= 0]
    return float(d.min()) if d.size else math.inf

