"""The streaming localiser: one query drive, frame by frame, against a map.

Per frame: k-NN retrieval over the whole map (FAISS) gives the observations; the SPRINT filter
updates the belief over the active set only; the most probable place is the decision. The
:class:`Localizer` serves both a vehicle streaming frames one at a time (:meth:`Localizer.step`)
and offline localisation of a whole drive (:meth:`Localizer.localize`, which batches its k-NN
searches). With ``record`` it keeps each frame's hits, and :meth:`Localizer.smooth_pass` re-decides
them from the smoothed posterior; the after-drive pipeline that decides what merges (calibration,
the deep pass, verification) is :mod:`sprint_map.merge.smoothing`.
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

from sprint_map.frontend.centring import Centring, DriveCentring
from sprint_map.hmm.cache import ComponentCache
from sprint_map.hmm.config import HMMConfig
from sprint_map.hmm.decision import Decision, is_unknown
from sprint_map.hmm.graph import GraphSource
from sprint_map.hmm.smoother import ForwardBackward
from sprint_map.hmm.sprint_filter import SprintFilter
from sprint_map.localize.gnss import GnssAid
from sprint_map.util.arrays import Descriptors, DescriptorsLike, SearchResult
from sprint_map.util.validation import validate_descriptors

__all__ = ["SEARCH_BATCH", "FrameDecision", "LocalizableMap", "Localizer", "LocalizerConfig",
           "LocalizerService", "MapView", "Timing", "nearest_hit", "recorded_k"]

#: Query rows per batched k-NN search in :meth:`Localizer.localize`.
SEARCH_BATCH = 256


class MapView(GraphSource, Protocol):
    """What a :class:`Localizer` reads of a map, through a view of its own
    (:class:`sprint_map.localize.stored_view.StoredMapView` is one).

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


class LocalizerConfig(Protocol):
    """What a :class:`Localizer` reads of a map's config (:class:`sprint_map.config.MapConfig`
    is one): the descriptor dimension and the HMM's parameters."""

    @property
    def dim(self) -> int: ...

    @property
    def hmm(self) -> HMMConfig: ...


class LocalizerService(Protocol):
    """What a :class:`Localizer` makes itself of, from a map's service API
    (:class:`sprint_map.facade.service.MapService` is one): a new :class:`MapView` for each
    localizer and a new drive's centring."""

    def view(self) -> MapView: ...

    def drive_centring(self) -> DriveCentring: ...


class LocalizableMap(Protocol):
    """A map a :class:`Localizer` can read (:class:`sprint_map.map.SprintMap` is one): its
    config and its service API."""

    @property
    def config(self) -> LocalizerConfig: ...

    @property
    def service(self) -> LocalizerService: ...


@dataclass(frozen=True)
class FrameDecision:
    """The answer for one query frame; ``seq_id``/``image_id`` are None for "no match".

    ``prob`` is the posterior mass of the decided place (the vertex, its temporal neighbours and
    the vertices joined to them by edges); for "no match" that of the best candidate, which
    ``best`` still names (``(seq_id, image_id)``, None when the map is empty). ``novel_prob``:
    the posterior of the "unmapped place" state (1 when the map is empty). ``distance``: the
    best retrieval hit's squared-L2 distance (inf when nothing was retrieved), which the merge
    rule compares with the drive's accepted matches; ``nearest``: that hit's vertex id (None
    then), where admission looks for a copy of the frame. ``contrast`` (smoothed matches only,
    else NaN): the best hit inside the decided place over the best elsewhere
    (:func:`sprint_map.hmm.decision.place_contrast`), below 1 when the place stands out.
    ``confirmed`` is False for a smoothed decision the merge rule may not merge: from the deep
    pass over ``smooth_k`` hits where the ``k``-hit decision was not accepted
    (:meth:`Localizer.smoothed`), on a run claiming a revisit the drive's own thumbnails deny
    (:meth:`sprint_map.merge.verification.RunVerifier.contradicted`), or beyond the gate of the
    frame's GNSS fix (:mod:`sprint_map.localize.gnss`). ``gnss_dist_m``: metres from the fix to
    the decided place's mapped position (NaN without either). ``verified``: True on a run that
    geometric verification on the thumbnails confirmed, merged even if a lookalike test refused it.
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
    gnss_dist_m: float = math.nan
    nearest: int | None = None

    @property
    def is_match(self) -> bool:
        return self.seq_id is not None

    def settled(self, min_confidence: float) -> FrameDecision:
        """This decision under the one rule for what an answer is
        (:func:`~sprint_map.hmm.decision.is_unknown` of ``prob`` and ``novel_prob``): a match
        the rule calls unknown becomes "no match" (``best`` keeps the place it named,
        ``contrast`` goes), everything else is returned as is. A ``verified`` match stays one:
        the thumbnails' geometry says the map holds the place, and the merge rule merges it.
        The causal and lagged answers are decided by that rule already; the smoothed ones
        carry the drive's calibrated ``novel_prob``, which the pass that named the place did
        not weigh. O(1)."""
        if (self.seq_id is None or self.verified
                or not is_unknown(self.prob, self.novel_prob, min_confidence)):
            return self
        best = self.best if self.best is not None else (self.seq_id, int(self.image_id or 0))
        return dataclasses.replace(self, seq_id=None, image_id=None, vertex_id=None, best=best,
                                   contrast=math.nan)

    def to_dict(self) -> dict[str, Any]:
        return {"frame": self.frame, "seq_id": self.seq_id, "image_id": self.image_id,
                "prob": round(float(self.prob), 6), "novel_prob": round(float(self.novel_prob), 6),
                "distance": round(self.distance, 6) if math.isfinite(self.distance) else None,
                "contrast": round(self.contrast, 6) if math.isfinite(self.contrast) else None,
                "confirmed": self.confirmed, "verified": self.verified,
                "gnss_dist_m": (round(self.gnss_dist_m, 3) if math.isfinite(self.gnss_dist_m)
                                else None)}


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
    gnss : GnssAid, optional
        The drive's GNSS fixes against the map's positions (:mod:`sprint_map.localize.gnss`):
        frame ``i`` (counted from the last :meth:`reset`) is weighed by fix ``i``.

    Notes
    -----
    Per-frame cost: one k-NN search over the map, plus the HMM update in
    O(W * n_active + nnz(U_active)) where ``n_active`` counts the vertices of the active
    components only, plus loading components that join the active set (LRU-cached); with
    ``gnss``, O(log n) more for the look-up of the fix among the map's n positions.
    """

    def __init__(self, smap: LocalizableMap, hmm: HMMConfig | None = None,
                 cache: ComponentCache | None = None, *, record: bool = False,
                 record_k: int | None = None, gnss: GnssAid | None = None,
                 in_map_space: bool = False) -> None:
        self.map = smap
        self.config = hmm or smap.config.hmm
        self.source = smap.service.view()
        # A cache may be shared by localizers over the same map (the server's sessions).
        self.cache = cache if cache is not None else ComponentCache(self.config.cache_budget_bytes)
        self.filter = SprintFilter(self.config, self.source, self.cache)
        self.timing = Timing()
        self.is_empty = self.source.vertices == 0
        self.frames_seen = 0
        #: Keep every frame's retrieval hits, for the smoothed decisions (O(k) per frame).
        self.record = record
        #: Neighbours searched and kept per recorded frame (None: :func:`recorded_k`; the
        #: service keeps ``k`` and has the smoothed decisions search the drive deeper at commit).
        self.record_k = record_k
        self.hits: list[tuple[np.ndarray, np.ndarray]] = []
        #: Called after every frame with ``(decision, hit ids, hit distances)`` (e.g. a
        #: :class:`sprint_map.localize.trace.TraceRecorder`, which reads ``filter`` too); None: nothing.
        self.observer: Callable[[FrameDecision, np.ndarray, np.ndarray], None] | None = None
        self.gnss = gnss
        #: The drive's centring (:mod:`sprint_map.frontend.centring`): every frame given is
        #: searched centred on the frames before it, in the map's space (``in_map_space``:
        #: the frames are a stored drive's rows, centred already, searched as they are).
        self.centring = (DriveCentring(Centring("none"), smap.config.dim) if in_map_space
                         else smap.service.drive_centring())

    def centred(self, descriptor: DescriptorsLike) -> Descriptors:
        """The next frame as this localizer searches it (nothing changes): what a caller of
        :meth:`step_hits` searches."""
        out: Descriptors = self.centring.preview(np.asarray(descriptor).reshape(1, -1))
        return out

    def reset(self) -> None:
        """Start a new query sequence."""
        self.centring = self.centring.fresh()
        self.filter.reset()
        self.timing = Timing()
        self.frames_seen = 0
        self.hits = []

    def smooth_pass(self, hits: Sequence[tuple[np.ndarray, np.ndarray]],
                    novelty: np.ndarray | None = None) -> list[FrameDecision]:
        """The decisions of the frames whose retrieval ``hits`` are given (one ``(ids,
        dists)`` per frame, nearest first), each from the smoothed posterior: forward-backward
        over the same sparse active set (:mod:`sprint_map.hmm.smoother`). ``novelty`` gives
        each frame's unmapped-place distance (``inf``: none); None keeps the config's.

        Notes
        -----
        One filter step and one backward step per frame, O(live); memory O(live) per frame.
        """
        fb = ForwardBackward(self.config, self.source, self.cache)
        for t, (ids, dists) in enumerate(hits):
            if novelty is not None:
                nd = float(novelty[t])
                fb.set_novelty_dist(nd if math.isfinite(nd) else None)
            cue = self.gnss.cue(t, ids, dists) if self.gnss is not None else None
            if cue is None:
                fb.forward(ids, dists)
            else:
                fb.forward(*cue)
        return [self.frame_decision(i, d, *nearest_hit(*hits[i]))
                for i, d in enumerate(fb.decisions())]

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
            self.is_empty = self.source.vertices == 0
            self.filter.invalidate(component_ids)
            self.source.mark_current()

    @contextmanager
    def pinned(self) -> Iterator[bool]:
        """Read one snapshot of the map in the block (:meth:`StoredMapView.pinned`): a writer
        committing meanwhile is not half seen. A map changed since the last snapshot (by a writer
        nobody told us of through :meth:`invalidate`) is caught up first; yields whether it
        had changed."""
        with self.source.pinned() as changed:
            self.is_empty = self.source.vertices == 0
            if changed:
                try:
                    self.filter.invalidate(None)
                except ValueError:  # belief on a removed sequence: start afresh from the hits
                    self.filter.reset()
            yield changed

    def step(self, descriptor: DescriptorsLike) -> FrameDecision:
        """Localise one frame (a vehicle streaming its images), given as described: it is
        centred here (:attr:`centring`); a refused frame changes nothing."""
        row = validate_descriptors(np.asarray(descriptor).reshape(1, -1), self.map.config.dim,
                                   self.frames_seen)
        centred, take = self.centring.pending(row)
        with self.pinned():
            if self.is_empty:
                decision = self._no_map_decision()
            else:
                start = time.perf_counter()
                dists, ids = self.source.search(centred, self.search_k)
                decision = self._update(ids[0], dists[0], (time.perf_counter() - start) * 1e3)
        take()
        return decision

    def step_hits(self, ids: np.ndarray, dists: np.ndarray, retrieval_ms: float = 0.0,
                  descriptor: DescriptorsLike | None = None) -> FrameDecision:
        """Localise one frame from its retrieval hits, searched by the caller (the service
        searches the frames of many sessions in one batch).

        The map's search answers a query the same alone or in a batch (bit for bit, see
        :func:`sprint_map.util.exact_search.certified_search`), so with the hits of
        ``smap.search(rows, config.k)`` made against the same map state this equals
        :meth:`step` of the row. The caller keeps the map from changing between the search and
        this call (the service's map gate). The hits are those of :meth:`centred`
        ``(descriptor)``, and ``descriptor`` (the frame as described) must be given when the
        map centres: the drive's centring takes it as its next frame (ValueError without).
        """
        if descriptor is None and self.centring.config.enabled:
            raise ValueError("step_hits needs the frame's descriptor: the drive is centred")
        with self.pinned():
            decision = (self._no_map_decision() if self.is_empty
                        else self._update(ids, dists, retrieval_ms))
        if descriptor is not None:
            self.centring.advance(np.asarray(descriptor).reshape(1, -1))
        return decision

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
        with self.pinned():
            for batch in batches:
                rows = self.centring.apply(batch)  # validated, then centred
                if self.is_empty:
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
        cue = (self.gnss.cue(self.frames_seen, ids[:k], dists[:k]) if self.gnss is not None
               else None)
        decision = (self.filter.step(ids[:k], dists[:k]) if cue is None
                    else self.filter.step(*cue))
        self.timing.hmm_ms.append((time.perf_counter() - start) * 1e3)
        self.timing.retrieval_ms.append(retrieval_ms)
        self.timing.active_vertices.append(int(decision.n_active_vertices))
        self.timing.active_components.append(int(decision.n_active_components))
        if self.record:
            self.hits.append((np.array(ids, copy=True), np.array(dists, copy=True)))
        frame = self.frames_seen
        self.frames_seen += 1
        out = self.frame_decision(frame, decision, *nearest_hit(ids, dists))
        if self.observer is not None:
            self.observer(out, ids, dists)
        return out

    def frame_decision(self, frame: int, decision: Decision, distance: float,
                       nearest: int | None = None) -> FrameDecision:
        out = self._frame_decision(frame, decision, distance, nearest)
        if self.gnss is None or out.vertex_id is None:
            return out
        gnss_dist, plausible = self.gnss.distance(frame, out.vertex_id)
        return dataclasses.replace(out, gnss_dist_m=gnss_dist,
                                   confirmed=out.confirmed and plausible)

    def _frame_decision(self, frame: int, decision: Decision, distance: float,
                        nearest: int | None) -> FrameDecision:
        if decision.vertex_id is None or decision.seq_id is None or decision.image_id is None:
            best = None
            if decision.candidate_id is not None:
                best = self.source.locate([decision.candidate_id])[0]
            return FrameDecision(frame, None, None, float(decision.prob), None, best,
                                 float(decision.sink_prob), distance, nearest=nearest)
        return FrameDecision(frame, int(decision.seq_id), int(decision.image_id),
                             float(decision.prob), int(decision.vertex_id),
                             (int(decision.seq_id), int(decision.image_id)),
                             float(decision.sink_prob), distance, float(decision.contrast),
                             nearest=nearest)

    def _no_map_decision(self) -> FrameDecision:
        self.timing.retrieval_ms.append(0.0)
        self.timing.hmm_ms.append(0.0)
        frame = self.frames_seen
        self.frames_seen += 1
        out = FrameDecision(frame, None, None, 0.0, novel_prob=1.0)
        if self.observer is not None:
            self.observer(out, np.empty(0, np.int64), np.empty(0, np.float32))
        return out


def recorded_k(config: HMMConfig) -> int:
    """Neighbours to search per frame for a drive whose hits are kept for the smoothed
    decisions: ``max(k, smooth_k)`` (``ingest``, ``localize --smooth``; the service keeps ``k``
    per frame and searches the drive ``smooth_k`` deep when it commits)."""
    return max(config.k, config.smooth_k)


def nearest_hit(ids: np.ndarray, dists: np.ndarray) -> tuple[float, int | None]:
    """A frame's best hit: its distance (squared L2) and vertex id (inf, None without a
    valid hit). O(k)."""
    ids = np.asarray(ids).ravel()
    valid = ids >= 0
    if not valid.any():
        return math.inf, None
    d = np.asarray(dists, dtype=np.float64).ravel()
    best = int(np.flatnonzero(valid)[np.argmin(d[valid])])
    return float(d[best]), int(ids[best])

