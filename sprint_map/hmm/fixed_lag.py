"""Fixed-lag smoothing over the sparse active set: each answer a few frames late, nearly smoothed.

A vehicle that can wait ``L`` frames for an answer gets frame ``t`` decided from
``P(state_t | frames 0..t+L)`` instead of the causal ``P(state_t | frames 0..t)``: once frame
``t + L`` has been filtered, a backward pass over the last ``L`` frames only (the recursion of
:mod:`sprint_map.hmm.smoother`, started from ``beta_{t+L} = 1``) gives ::

    beta_{t|t+L} = B_{t+1} ... B_{t+L} 1,        gamma_{t|t+L} = normalise(alpha_t * beta_{t|t+L})

where ``B_s`` is one backward step (:func:`~sprint_map.hmm.smoother.backward_step`: the adjoint
of the propagation on the support of ``alpha_{s-1}``, the likelihoods of frame ``s``). The
filter keeps running forward; only the live belief of the last ``L + 1`` frames is kept.

* ``L = 0`` is the causal filter: the answer is :meth:`SprintFilter.decide` of the frame.
* ``L >= 1``: the answer for frame ``t`` is the decision
  (:func:`~sprint_map.hmm.smoother.decide_posterior`) of ``gamma_{t|t+L}``, with the contrast
  of a match over the frames ``t - 2 .. t + 2`` seen so far, reported on the drive of the
  previous answer where the place holds it (consecutive answers follow one drive).
* :meth:`FixedLagSmoother.flush` (the end of a drive) answers the frames still waiting from one
  backward pass from the last frame, each reported on the drive of the next, exactly as
  :meth:`ForwardBackward.decisions <sprint_map.hmm.smoother.ForwardBackward.decisions>`
  decides them. So with ``L`` at least the drive's length every answer comes from the flush
  and equals the smoothed pass over the same hits, float for float.

Cost per frame: one filter update, the backward operator from it onto the frame before (built
as the frame is pushed, so every answer costs the same), ``L`` applications of the waiting
frames' operators (each O(live); nothing is sized by the map) and one decision. Memory: the
live belief and the hits of ``L + 3`` frames, whatever the drive's length, plus one dense
decision vector per active component (as the filter's own belief).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable

import numpy as np

from sprint_map.hmm.cache import ComponentCache
from sprint_map.hmm.config import HMMConfig
from sprint_map.hmm.decision import Decision
from sprint_map.hmm.graph import GraphSource
from sprint_map.hmm.observation import ObservationModel, sequence_first_of
from sprint_map.hmm.smoother import (
    DecisionScratch,
    FrameBelief,
    Parts,
    backward_operator,
    backward_step,
    decide_posterior,
    gamma_of,
    nearest_hits,
)
from sprint_map.hmm.sprint_filter import SprintFilter

__all__ = ["MAX_LAG", "FixedLagSmoother", "check_lag"]

#: The largest lag accepted (frames): each frame costs ``L`` backward steps, and a lagged
#: drive holds ``L`` frames' beliefs (tens of KB each on a city map: ~24 MB at this bound);
#: beyond this (100 s at 10 Hz), the commit's whole-drive smoothing is the answer.
MAX_LAG = 1_000


def check_lag(lag: object) -> int:
    """``lag`` as a number of frames, or ``ValueError`` naming the accepted range
    ``0 .. MAX_LAG`` (a bool or a non-integer is not a lag)."""
    if isinstance(lag, bool) or not isinstance(lag, int | np.integer):
        raise ValueError(f"lag must be a whole number of frames, got {lag!r}")
    if not 0 <= int(lag) <= MAX_LAG:
        raise ValueError(f"lag must be between 0 and {MAX_LAG} frames, got {int(lag)}")
    return int(lag)


class FixedLagSmoother:
    """Decisions of a query sequence with a fixed lag of ``lag`` frames (module docstring).

    ``config`` and ``source`` as for :class:`SprintFilter`; ``cache`` a shared component
    cache; ``lag`` the frames of delay, ``0 .. MAX_LAG``.

    Notes
    -----
    :meth:`push` costs one filter update, ``lag`` backward steps and one decision, all
    O(live); memory is O(lag * live + lag * k).

    Examples
    --------
    >>> import numpy as np
    >>> from sprint_map.hmm import HMMConfig, MemoryGraphSource
    >>> fl = FixedLagSmoother(HMMConfig(), MemoryGraphSource([50, 50]), lag=2)
    >>> answers = [fl.push(np.array([10 + t, 70]), np.array([0.1, 0.5])) for t in range(5)]
    >>> [None if d is None else d.image_id for d in answers]
    [None, None, 10, 11, 12]
    >>> [d.image_id for d in fl.flush()]
    [13, 14]
    """

    def __init__(self, config: HMMConfig, source: GraphSource,
                 cache: ComponentCache | None = None, *, lag: int) -> None:
        self.lag = check_lag(lag)
        self.config = config
        self.source = source
        self.filter = SprintFilter(config, source, cache)
        self._obs = ObservationModel(config, sequence_first_of(source))
        self._scratch = DecisionScratch()
        self.reset()

    def reset(self) -> None:
        """Start a new query sequence (nothing waits for an answer any more)."""
        self.filter.reset()
        self._obs.reset()
        #: The frames not answered yet, oldest first (at most ``lag`` between pushes).
        self._frames: deque[FrameBelief] = deque()
        #: The ``k`` nearest hits of the waiting frames and of the (up to) two answered before.
        self._nearest: deque[tuple[list[int], list[float]]] = deque()
        self._prefer: int | None = None
        #: :meth:`FrameBelief.held_bytes` of each waiting frame (a frame is counted again
        #: once the next one built its backward operator), and their sum.
        self._frame_bytes: deque[int] = deque()
        self._held = 0
        #: Frames pushed, and frames answered (the next answer is for frame ``answered``).
        self.pushed = 0
        self.answered = 0

    @property
    def held_bytes(self) -> int:
        """Bytes the waiting frames hold (:meth:`FrameBelief.held_bytes`, with their nearest
        hits): what a lagged session keeps beyond its descriptors, about ``lag`` times a
        frame's belief. O(1)."""
        return self._held

    def _count(self, frame: FrameBelief, again: bool = False) -> None:
        """Count ``frame`` (the newest waiting one) in :attr:`held_bytes`; ``again``: it was
        counted already and has grown."""
        size = frame.held_bytes() + 96 * self.config.k  # its k nearest hits, boxed
        if again:
            self._held -= self._frame_bytes.pop()
        self._frame_bytes.append(size)
        self._held += size

    def _recount(self) -> None:
        self._frame_bytes = deque()
        self._held = 0
        for frame in self._frames:
            self._count(frame)

    @property
    def waiting(self) -> int:
        """Frames pushed and not answered yet (``lag`` once the drive is that long)."""
        return len(self._frames)

    def push(self, hit_ids: np.ndarray, hit_dists: np.ndarray) -> Decision | None:
        """Filter one frame; return the decision of frame ``pushed - 1 - lag`` (None while
        fewer than ``lag + 1`` frames were pushed).

        Raises
        ------
        ValueError
            Malformed hits or a hit the source does not know (as :meth:`SprintFilter.update`;
            nothing changes).
        """
        if self.lag == 0:
            self.filter.update(hit_ids, hit_dists)
            self.pushed += 1
            self.answered += 1
            return self.filter.decide()
        vids, vdists, lik, sink_lik, _ = self._obs.evaluate(np.asarray(hit_ids),
                                                            np.asarray(hit_dists))
        self.filter.update_observed(vids, lik, sink_lik)  # a bad hit raises before any change
        self.pushed += 1
        frame = FrameBelief.of_belief(self.filter.laid_belief(), vids, vdists, lik, sink_lik)
        self._frames.append(frame)
        self._nearest.append(nearest_hits(frame, self.config.k))
        if len(self._frames) >= 2:
            # the backward step's operator onto the previous frame, built now: every answer
            # then builds none, the first one (after ``lag`` pushes) included
            before = self._frames[-2]
            before.pulls = backward_operator(before, frame)
            self._count(before, again=True)
        self._count(frame)
        if len(self._frames) <= self.lag:
            return None
        return self._answer_oldest()

    def _answer_oldest(self) -> Decision:
        frames = self._frames
        beta = np.ones(frames[-1].starts()[-1])
        beta_sink = bound = 1.0
        for i in range(len(frames) - 2, -1, -1):
            beta, beta_sink, bound = backward_step(self.config, frames[i], frames[i + 1], beta,
                                                   beta_sink, keep=True, bound=bound)
        gamma, sink = gamma_of(frames[0], beta, beta_sink)
        nearest = list(self._nearest)
        decision = decide_posterior(self.config, frames[0], gamma, sink, self._scratch,
                                    self._prefer, nearest, len(nearest) - len(frames))
        if decision.candidate_id is not None and decision.seq_id is not None:
            self._prefer = decision.seq_id
        frames.popleft()
        self._held -= self._frame_bytes.popleft()
        while len(self._nearest) > len(frames) + 2:
            self._nearest.popleft()
        self.answered += 1
        return decision

    def pending(self) -> list[Decision]:
        """The answers :meth:`flush` would give now, without giving them: nothing changes (a
        commit that may yet be refused reads them; the drive may go on). O(waiting)."""
        frames = self._frames
        if not frames:
            return []
        nearest = list(self._nearest)
        offset = len(nearest) - len(frames)
        out: list[Decision] = []
        prefer: int | None = None
        for i, (gamma, sink) in zip(range(len(frames) - 1, -1, -1), self._posteriors(),
                                    strict=True):
            decision = decide_posterior(self.config, frames[i], gamma, sink, self._scratch,
                                        prefer, nearest, offset + i)
            if decision.candidate_id is not None and decision.seq_id is not None:
                prefer = decision.seq_id
            out.append(decision)
        out.reverse()
        return out

    def flush(self) -> list[Decision]:
        """Answer every waiting frame now, in frame order (the end of a drive): one backward
        pass from the last frame pushed, each frame reported on the drive of the next, as
        :meth:`ForwardBackward.decisions` does. The belief is kept: later frames go on.

        Notes
        -----
        O(waiting) backward steps and decisions (:meth:`pending`, then consumed).
        """
        out = self.pending()
        if not out:
            return []
        last = out[-1]
        if last.candidate_id is not None and last.seq_id is not None:
            self._prefer = last.seq_id
        self.answered += len(out)
        self._frames.clear()
        self._frame_bytes.clear()
        self._held = 0
        while len(self._nearest) > 2:
            self._nearest.popleft()
        return out

    def _posteriors(self) -> Iterable[tuple[np.ndarray, float]]:
        """The smoothed posterior of every waiting frame given all pushed, last first
        (:func:`gamma_of`)."""
        frames = self._frames
        beta = np.ones(frames[-1].starts()[-1])
        beta_sink = 1.0
        yield gamma_of(frames[-1], beta, beta_sink)
        bound = 1.0
        for i in range(len(frames) - 2, -1, -1):
            beta, beta_sink, bound = backward_step(self.config, frames[i], frames[i + 1], beta,
                                                   beta_sink, keep=True, bound=bound)
            yield gamma_of(frames[i], beta, beta_sink)

    def invalidate(self, component_ids: Iterable[int] | None = None) -> None:
        """Re-read components after the map changed (:meth:`SprintFilter.invalidate`), and
        re-map the waiting frames' beliefs onto the current components by vertex id.

        A belief on a vertex the source no longer knows (a removed sequence) cannot be
        re-mapped: the filter then starts afresh from the next frame's hits and such a
        waiting frame keeps only its sink (answered "no match"); every frame is still
        answered once, in order.

        Notes
        -----
        O(lag * live) plus the loads of the affected components.
        """
        try:
            self.filter.invalidate(component_ids)
        except ValueError:
            self.filter.reset()
        self._frames = deque(self._remapped(frame) for frame in self._frames)
        self._recount()

    def _remapped(self, frame: FrameBelief) -> FrameBelief:
        """``frame`` with its parts on the source's current components."""
        vid_parts = [trans.vertex_of_slots(slots) for trans, slots, _ in frame.parts]
        if not vid_parts:
            return frame
        vids = np.concatenate(vid_parts)
        vals = np.concatenate([alpha for _, _, alpha in frame.parts])
        parts: Parts = []
        if vids.size:
            try:
                comp_ids = np.asarray(self.source.components_of(vids))
            except ValueError:  # a vertex of a removed sequence: only the sink is left
                return FrameBelief([], 1.0, frame.hit_ids, frame.hit_dists, frame.hit_lik,
                                   frame.sink_lik)
            for cid in np.unique(comp_ids).tolist():
                trans = self.filter.transition(int(cid))
                sel = comp_ids == cid
                slots = trans.slots_of(vids[sel])
                order = np.argsort(slots, kind="stable")
                parts.append((trans, slots[order], vals[sel][order]))
        return FrameBelief(parts, frame.sink, frame.hit_ids, frame.hit_dists, frame.hit_lik,
                           frame.sink_lik)
