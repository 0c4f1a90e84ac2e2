"""Streaming answers a fixed number of frames late: a vehicle that can wait ``lag`` frames.

:class:`LaggedLocalizer` localises a drive frame by frame like
:class:`~sprint_map.localize.localizer.Localizer`, but answers frame ``t`` only once frame
``t + lag`` has been seen, from the fixed-lag smoothed posterior
(:class:`~sprint_map.hmm.fixed_lag.FixedLagSmoother`: the forward belief at ``t + lag`` and a
backward pass over the last ``lag`` frames). Each :meth:`LaggedLocalizer.step` answers at most
one frame, in frame order; :meth:`LaggedLocalizer.flush` answers the last ``lag`` at the end.

The model: with ``lag = 0`` every call is the :class:`Localizer`'s, so the answers are the
causal ones, exactly. With ``lag >= 1`` the filter reads each frame's ``max(k, smooth_k)``
nearest hits (the model of the after-drive pipeline's deep pass, which the lagged answers
tend to; on Nordland the ``k``-hit model's smoothed ceiling is 2-6 points lower), so with
``lag`` at least the drive's length the answers are :meth:`Localizer.smooth_pass` over the
hits a ``record=True`` localizer keeps (``docs/hmm.md``, "Fixed lag").
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

import numpy as np

from sprint_map.errors import InputError
from sprint_map.hmm.cache import ComponentCache
from sprint_map.hmm.config import HMMConfig
from sprint_map.hmm.decision import Decision
from sprint_map.hmm.fixed_lag import MAX_LAG, FixedLagSmoother, check_lag
from sprint_map.localize.localizer import (
    SEARCH_BATCH,
    FrameDecision,
    LocalizableMap,
    Localizer,
    Timing,
    nearest_hit,
    recorded_k,
)
from sprint_map.util.arrays import DescriptorsLike
from sprint_map.util.validation import validate_descriptors

__all__ = ["MAX_LAG", "LaggedLocalizer", "validate_lag"]

_NO_HITS = (np.empty(0, np.int64), np.empty(0, np.float32))


def validate_lag(lag: object, *, whole_drive: bool = False, fixes: bool = False,
                 flags: bool = False) -> int:
    """``lag`` as frames (``0 .. MAX_LAG``), or :class:`InputError` with one clear line.

    The rule of the lag, for the facade and the CLI alike: a lag answers frames as the drive
    goes, so a non-zero one excludes ``whole_drive`` (smoothing the whole drive, its
    thumbnails or a trace) and GNSS ``fixes``. ``flags``: word the refusal as the CLI's
    options (``--smooth``, ``--positions``).
    """
    try:
        lag = check_lag(lag)
    except ValueError as exc:
        raise InputError(str(exc)) from None
    if lag and whole_drive:
        raise InputError("--lag answers frames as the drive goes: it cannot be combined with "
                         "--smooth (the whole drive) or --trace" if flags else
                         "a lag answers frames as the drive goes: it cannot be combined with "
                         "smoothing the whole drive, thumbnails or a trace")
    if lag and fixes:
        raise InputError("--lag does not weigh GNSS fixes: drop --positions, or --lag" if flags
                         else "GNSS fixes are not supported with a lag: localise with "
                         "--positions without --lag, or with --lag without positions")
    return lag


class LaggedLocalizer:
    """Localise one query drive, answering each frame ``lag`` frames late.

    ``smap``: the map (read-only is enough); ``lag``: frames of delay, ``0 .. MAX_LAG``
    (:class:`InputError` otherwise); ``hmm``: model parameters (default the map's own);
    ``cache``: where loaded components are kept (the server's sessions share one);
    ``record``: keep each frame's hits for the after-drive decisions, as :class:`Localizer`
    does. :attr:`localizer` searches (and, with ``lag = 0``, decides); its ``source``,
    ``timing``, recorded ``hits`` and ``frames_seen`` are this drive's.

    Notes
    -----
    Per frame: one k-NN search of ``max(k, smooth_k)`` neighbours (``k`` with ``lag = 0``),
    then :meth:`FixedLagSmoother.push`: one filter update, ``lag`` backward steps and one
    decision, all O(live). Memory O(lag * (live + k)) beyond the localizer's.
    """

    def __init__(self, smap: LocalizableMap, lag: int, hmm: HMMConfig | None = None,
                 cache: ComponentCache | None = None, *, record: bool = False) -> None:
        self.lag = validate_lag(lag)
        config = hmm or smap.config.hmm
        depth = recorded_k(config) if self.lag else None
        self.localizer = Localizer(smap, config, cache, record=record, record_k=depth)
        self.depth = depth or config.k
        self.smoother = (FixedLagSmoother(config, self.localizer.source, self.localizer.cache,
                                          lag=self.lag) if self.lag else None)
        #: Best hit (distance, vertex id) of every frame not answered yet, oldest first.
        self._best_hits: deque[tuple[float, int | None]] = deque()

    @property
    def timing(self) -> Timing:
        """Per-frame timing: each frame's ``hmm_ms`` includes its backward pass and the
        decision it answered."""
        return self.localizer.timing

    @property
    def frames_seen(self) -> int:
        return self.localizer.frames_seen

    @property
    def waiting(self) -> int:
        """Frames seen and not answered yet."""
        return self.smoother.waiting if self.smoother is not None else 0

    def reset(self) -> None:
        """Start a new query drive (frames still waiting are dropped)."""
        self.localizer.reset()
        if self.smoother is not None:
            self.smoother.reset()
        self._best_hits.clear()

    def invalidate(self, component_ids: Iterable[int] | None = None) -> None:
        """The map changed (a commit): see :meth:`Localizer.invalidate`; the frames waiting
        for an answer are re-mapped too (:meth:`FixedLagSmoother.invalidate`)."""
        ids = None if component_ids is None else list(component_ids)
        self.localizer.invalidate(ids)
        if self.smoother is not None:
            with self.localizer.source.pinned():
                self.smoother.invalidate(ids)

    def step(self, descriptor: DescriptorsLike) -> FrameDecision | None:
        """Localise one frame; return the answer of frame ``frames_seen - 1 - lag`` (None
        while fewer than ``lag + 1`` frames were seen)."""
        if self.smoother is None:
            return self.localizer.step(descriptor)
        row = validate_descriptors(np.asarray(descriptor).reshape(1, -1),
                                   self.localizer.map.config.dim, self.localizer.frames_seen)
        centred, take = self.localizer.centring.pending(row)
        with self._pinned():
            if self.localizer.is_empty:
                answer = self._update(*_NO_HITS, 0.0)
            else:
                start = time.perf_counter()
                dists, ids = self.localizer.source.search(centred, self.depth)
                answer = self._update(ids[0], dists[0], (time.perf_counter() - start) * 1e3)
        take()
        return answer

    def step_hits(self, ids: np.ndarray, dists: np.ndarray, retrieval_ms: float = 0.0,
                  descriptor: DescriptorsLike | None = None) -> FrameDecision | None:
        """:meth:`step` from the frame's hits, searched by the caller with
        :attr:`depth` neighbours for :meth:`Localizer.centred` ``(descriptor)`` (as
        :meth:`Localizer.step_hits`)."""
        if self.smoother is None:
            return self.localizer.step_hits(ids, dists, retrieval_ms, descriptor)
        centring = self.localizer.centring
        if descriptor is None and centring.config.enabled:
            raise ValueError("step_hits needs the frame's descriptor: the drive is centred")
        with self._pinned():
            answer = (self._update(*_NO_HITS, retrieval_ms) if self.localizer.is_empty
                      else self._update(ids, dists, retrieval_ms))
        if descriptor is not None:
            centring.advance(np.asarray(descriptor).reshape(1, -1))
        return answer

    def flush(self) -> list[FrameDecision]:
        """Answer every frame still waiting (the end of the drive), in frame order."""
        if self.smoother is None or not self.smoother.waiting:
            return []
        first = self.smoother.answered
        start = time.perf_counter()
        with self.localizer.pinned():
            decisions = self.smoother.flush()
        out = [self._answer(first + i, d) for i, d in enumerate(decisions)]
        self.timing.smooth_ms += (time.perf_counter() - start) * 1e3
        return out

    def pending(self) -> list[FrameDecision]:
        """The answers :meth:`flush` would give now, in frame order, without giving them:
        nothing changes, so a commit that is refused leaves the drive as it was and the next
        frames are answered as if it had never been tried. O(waiting) backward steps."""
        if self.smoother is None or not self.smoother.waiting:
            return []
        first = self.smoother.answered
        with self.localizer.pinned():
            decisions = self.smoother.pending()
        return [self.localizer.frame_decision(first + i, d, *best)
                for i, (d, best) in enumerate(zip(decisions, self._best_hits, strict=True))]

    def localize(self, descriptors: DescriptorsLike | Iterable[DescriptorsLike]
                 ) -> list[FrameDecision]:
        """Every frame's answer, in frame order (the last ``lag`` flushed at the end)."""
        return list(self.iter_localize(descriptors))

    def iter_localize(self, descriptors: DescriptorsLike | Iterable[DescriptorsLike]
                      ) -> Iterator[FrameDecision]:
        """Like :meth:`localize`, yielding answers as they are made; searches are batched
        (:data:`~sprint_map.localize.localizer.SEARCH_BATCH` rows) against one snapshot."""
        if self.smoother is None:
            yield from self.localizer.iter_localize(descriptors)
            return
        batches = (
            (descriptors[i : i + SEARCH_BATCH] for i in range(0, len(descriptors), SEARCH_BATCH))
            if isinstance(descriptors, np.ndarray) else descriptors
        )
        with self._pinned():
            for batch in batches:
                rows = self.localizer.centring.apply(batch)  # validated, then centred
                if self.localizer.is_empty:
                    for _ in range(len(rows)):
                        if (answer := self._update(*_NO_HITS, 0.0)) is not None:
                            yield answer
                    continue
                start = time.perf_counter()
                dists, ids = self.localizer.source.search(rows, self.depth)
                share = (time.perf_counter() - start) * 1e3 / len(rows)
                for i in range(len(rows)):
                    if (answer := self._update(ids[i], dists[i], share)) is not None:
                        yield answer
            yield from self.flush()

    @contextmanager
    def _pinned(self) -> Iterator[bool]:
        """:meth:`Localizer.pinned`; a map changed underneath re-maps the waiting frames."""
        with self.localizer.pinned() as changed:
            if changed and self.smoother is not None:
                self.smoother.invalidate(None)
            yield changed

    def _update(self, ids: np.ndarray, dists: np.ndarray, retrieval_ms: float
                ) -> FrameDecision | None:
        assert self.smoother is not None
        loc = self.localizer
        start = time.perf_counter()
        decision = self.smoother.push(ids[:self.depth], dists[:self.depth])
        self._best_hits.append(nearest_hit(ids, dists) if len(ids) else (math.inf, None))
        answer = (self._answer(self.smoother.answered - 1, decision)
                  if decision is not None else None)
        timing = loc.timing
        timing.hmm_ms.append((time.perf_counter() - start) * 1e3)
        timing.retrieval_ms.append(retrieval_ms)
        timing.active_vertices.append(int(self.smoother.filter.n_active_vertices))
        timing.active_components.append(int(self.smoother.filter.n_active_components))
        if loc.record:
            loc.hits.append((np.array(ids, copy=True), np.array(dists, copy=True)))
        loc.frames_seen += 1
        return answer

    def _answer(self, frame: int, decision: Decision) -> FrameDecision:
        """Frame ``frame``'s answer (the oldest waiting: its best hit is the first kept)."""
        return self.localizer.frame_decision(frame, decision, *self._best_hits.popleft())
