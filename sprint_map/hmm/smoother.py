"""Forward-backward smoothing over the sparse active set: decisions that use the whole drive.

A vehicle needs each answer now, so :class:`~sprint_map.hmm.SprintFilter` is causal: frame
``t`` is decided from frames ``0..t``. A merge is decided once the whole drive has been seen
(``ingest`` localises the drive before it commits), so it can use the drive's future as well:
the smoothed posterior ``gamma_t(i) = P(state_t = i | frames 0..N-1)``.

Model (the filter's, written as one transition per frame; ``s = 1 - eps - nu``)::

    T_t(i -> j) = s A(i, j) + eps / n_t [j is a hit of frame t] + nu [j = sink]
    alpha_t     = normalise( (T_t^T alpha_{t-1}) * e_t )        (the filter's update)
    beta_t(i)   = sum_j T_{t+1}(i -> j) e_{t+1}(j) beta_{t+1}(j)
                = s (A m_{t+1})(i) + C_{t+1},   m_{t+1} = e_{t+1} * beta_{t+1}
    C_{t+1}     = eps / n_{t+1} sum_{hits h} m_{t+1}(h) + nu m_{t+1}(sink)
    gamma_t     = normalise( alpha_t * beta_t )

``A`` is the propagation (own window, edges, overflow to the sink; the sink keeps its mass)
and ``e_t`` the frame's likelihood ratios (1 for every vertex that is not a hit). A frame
without hits sends ``eps`` to the sink too.

Sparsity: ``alpha_t`` is the filter's belief, held on its live windows only (pruning and
trimming drop the rest), so ``beta_t`` is needed only there, and ``m_{t+1}`` is non-zero only on
the support of ``alpha_{t+1}``: a state the filter dropped is one the (truncated) model killed.
The backward step is :meth:`ComponentTransition.pull` over the same support, so it costs what a
forward step costs and never grows with the map. With pruning and trimming off the smoothed
posterior equals the full-graph forward-backward (:meth:`FullGraphFilter.smooth`), which the
tests check.

Memory: the frame's live belief (slots and values, O(live)) for every frame of the drive,
plus its hits; decisions are made frame by frame during the backward pass.
"""

from __future__ import annotations

import sys
from bisect import bisect_left, bisect_right
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from sprint_map.hmm.cache import ComponentCache
from sprint_map.hmm.config import HMMConfig
from sprint_map.hmm.decision import BeliefView, Decision, decide, place_contrast, top_positions
from sprint_map.hmm.graph import GraphSource
from sprint_map.hmm.observation import ObservationModel, sequence_first_of
from sprint_map.hmm.sprint_filter import SprintFilter
from sprint_map.hmm.transition import (
    ComponentTransition,
    PullOperator,
    parts_pull_operator,
    slot_bases,
    slot_space,
)

__all__ = ["BackwardOperator", "ConfirmedRivals", "DecisionScratch", "FrameBelief",
           "ForwardBackward", "Parts", "RESCALE_ABOVE", "RESCALE_BELOW", "RIVAL_CONFIRMATIONS",
           "RIVAL_MIN_WEIGHT", "RIVAL_SLACK", "backward_operator",
           "backward_step", "decide_posterior", "gamma_of", "nearest_hits",
           "smooth"]

#: A frame's hit elsewhere in the map counts as a rival of its decided place (contrast) only if
#: this many of the 4 frames around it have a hit where the same drive would be then ...
RIVAL_CONFIRMATIONS = 2
#: ... within this many images.
RIVAL_SLACK = 2
#: A hit another cue weighs below this (GNSS: far beyond the gate of the frame's fix) is ruled
#: out as a place of the frame: it is no rival of the decided place (contrast).
RIVAL_MIN_WEIGHT = 0.01


@dataclass(slots=True)
class FrameBelief:
    """What the forward pass keeps of one frame.

    Attributes
    ----------
    parts : list of (ComponentTransition, slots, alpha)
        The filtered posterior on the live slots of each active component.
    sink : float
        The sink's filtered posterior.
    hit_ids : list of int
        The frame's distinct valid hits.
    hit_dists : list of float
        Their squared-L2 distances (for the decisions' contrast).
    hit_lik : list of float
        Their likelihood ratios.
    sink_lik : float
        The sink's likelihood ratio.
    ruled_out : frozenset of int
        Hits another cue weighed below :data:`RIVAL_MIN_WEIGHT` (no rivals).
    """

    parts: list[tuple[ComponentTransition, np.ndarray, np.ndarray]]
    sink: float
    hit_ids: list[int]
    hit_dists: list[float]
    hit_lik: list[float]
    sink_lik: float
    ruled_out: frozenset[int] = frozenset()
    #: :meth:`held_hits`, made on first use (None until then).
    hit_layout: tuple[np.ndarray, np.ndarray] | None = None
    #: The backward step's operator from the next frame onto this one, when kept
    #: (:func:`backward_step` with ``keep``; :func:`backward_operator`).
    pulls: BackwardOperator | None = None
    #: Where each part starts in the frame's values laid end to end (and their total, last);
    #: made on first use by :meth:`starts`.
    part_starts: list[int] | None = None
    #: The parts' alpha laid end to end; made on first use by :meth:`values`.
    laid: np.ndarray | None = None
    #: The parts' slots in one slot space (:func:`~sprint_map.hmm.transition.slot_space`)
    #: and their transitions, in order; made on first use by :meth:`space`.
    spaced: tuple[np.ndarray, list[ComponentTransition]] | None = None

    @classmethod
    def of_belief(cls, belief: tuple[list[ComponentTransition], np.ndarray, np.ndarray,
                                     list[int], float],
                  hit_ids: list[int], hit_dists: list[float], hit_lik: list[float],
                  sink_lik: float, ruled_out: frozenset[int] = frozenset()) -> FrameBelief:
        """A frame from :meth:`SprintFilter.laid_belief
        <sprint_map.hmm.sprint_filter.SprintFilter.laid_belief>` (its parts views of it:
        nothing is laid end to end again) and its hits. O(parts)."""
        transitions, slots, values, starts, sink = belief
        parts = [(trans, slots[starts[i]:starts[i + 1]], values[starts[i]:starts[i + 1]])
                 for i, trans in enumerate(transitions)]
        return cls(parts, sink, hit_ids, hit_dists, hit_lik, sink_lik, ruled_out,
                   part_starts=starts, laid=values)

    def starts(self) -> list[int]:
        """Where each part's values start when the parts are laid end to end, then their
        total (``len(parts) + 1`` numbers; cached)."""
        if self.part_starts is None:
            out = [0]
            for _, slots, _ in self.parts:
                out.append(out[-1] + len(slots))
            self.part_starts = out
        return self.part_starts

    def held_bytes(self) -> int:
        """Bytes this frame holds of its own: its arrays (each buffer once, a view counted by
        the array it views), its hit lists and its backward operator; not the components'
        transitions, which the cache holds for every frame. O(parts + hits)."""
        seen: set[int] = set()
        total = 0
        todo: list[object] = [self.parts, self.hit_ids, self.hit_dists, self.hit_lik,
                              self.hit_layout, self.pulls, self.part_starts, self.laid,
                              None if self.spaced is None else self.spaced[0]]
        while todo:
            obj = todo.pop()
            if obj is None or isinstance(obj, ComponentTransition | float | int | bool):
                continue
            if isinstance(obj, np.ndarray):
                while isinstance(obj.base, np.ndarray):
                    obj = obj.base
                if id(obj) not in seen:
                    seen.add(id(obj))
                    total += obj.nbytes + 112  # the array object itself
            elif isinstance(obj, list | tuple):
                total += sys.getsizeof(obj)
                if obj and isinstance(obj[0], float | int):
                    total += 32 * len(obj)  # boxed numbers
                else:
                    todo.extend(obj)
            elif hasattr(obj, "__slots__"):  # the backward operator and its pull
                total += sys.getsizeof(obj)
                todo.extend(getattr(obj, name, None) for name in type(obj).__slots__)
        return total

    def values(self) -> np.ndarray:
        """The parts' alpha laid end to end (cached; O(live) once)."""
        if self.laid is None:
            alphas = [alpha for _, _, alpha in self.parts]
            self.laid = (_EMPTY_VALS if not alphas else alphas[0] if len(alphas) == 1
                         else np.concatenate(alphas))
        return self.laid

    def split(self, values: np.ndarray) -> Parts:
        """``values`` laid end to end over this frame's parts, as parts (views, no copy)."""
        starts = self.starts()
        return [(trans, slots, values[starts[i]:starts[i + 1]])
                for i, (trans, slots, _) in enumerate(self.parts)]

    def space(self) -> tuple[np.ndarray, list[ComponentTransition]]:
        """The parts' slots laid in one slot space
        (:func:`~sprint_map.hmm.transition.slot_space`) and the parts' transitions, in order
        (cached; O(live) once)."""
        if self.spaced is None:
            self.spaced = (slot_space([(trans, slots) for trans, slots, _ in self.parts]),
                           [trans for trans, _, _ in self.parts])
        return self.spaced

    def held_hits(self) -> tuple[np.ndarray, np.ndarray]:
        """The hits this frame's parts hold: their positions in the parts' slots laid end to
        end (ascending) and their likelihood ratios (cached; O(hits log live + parts) once,
        plus O(hits log S) for a part of S > 1 sequences)."""
        if self.hit_layout is None:
            self.hit_layout = _held_hits(self.parts, self.space()[0], self.hit_ids,
                                         self.hit_lik)
        return self.hit_layout


def _held_hits(parts: Parts, live: np.ndarray, hit_ids: list[int], hit_lik: list[float]
               ) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`FrameBelief.held_hits`: every hit's slot found in the parts' one slot space
    (``live``, :meth:`FrameBelief.space`), then its position there."""
    if not hit_ids or not parts or not live.size:
        return _EMPTY_SLOTS, _EMPTY_VALS
    ids = np.asarray(hit_ids, dtype=np.int64)
    where = np.full(ids.size, -1, dtype=np.int64)  # each hit's slot in the one space
    lone: list[tuple[int, int, int]] = []  # one-sequence parts: (first vertex, end, slot 0)
    transitions = [trans for trans, _, _ in parts]
    for trans, offset in zip(transitions, slot_bases(transitions), strict=True):
        if len(trans.ranges) == 1:
            first, length, slot = trans.ranges[0]
            lone.append((first, first + length, slot + offset))
        else:
            at, held = trans.held_slots(ids)
            where[at] = held + offset
    if lone:
        firsts, ends, slot0 = np.array(sorted(lone), dtype=np.int64).T
        r = np.maximum(firsts.searchsorted(ids, "right") - 1, 0)
        inside = ((ids >= firsts[r]) & (ids < ends[r])).nonzero()[0]
        where[inside] = ids[inside] - firsts[r[inside]] + slot0[r[inside]]
    hit = (where >= 0).nonzero()[0]
    if not hit.size:
        return _EMPTY_SLOTS, _EMPTY_VALS
    pos = np.minimum(live.searchsorted(where[hit]), live.size - 1)
    held = live[pos] == where[hit]
    pos, hit = pos[held], hit[held]
    order = np.argsort(pos)
    return pos[order], np.asarray(hit_lik, dtype=np.float64)[hit[order]]


class ForwardBackward:
    """Smoothed decisions for a whole query sequence over a :class:`GraphSource`.

    Per frame, :meth:`forward` costs one filter step plus O(live), the backward pass the same
    (:meth:`ComponentTransition.pull`) plus one decision; nothing is sized by the map.

    Parameters
    ----------
    config : HMMConfig
    source : GraphSource
    cache : ComponentCache, optional
        Shared component cache (e.g. the causal localizer's).

    Examples
    --------
    >>> import numpy as np
    >>> from sprint_map.hmm import HMMConfig, MemoryGraphSource
    >>> fb = ForwardBackward(HMMConfig(), MemoryGraphSource([50, 50]))
    >>> for t in range(5):
    ...     fb.forward(np.array([10 + t, 70]), np.array([0.1, 0.5]))
    >>> [d.image_id for d in fb.decisions()]
    [10, 11, 12, 13, 14]
    """

    def __init__(self, config: HMMConfig, source: GraphSource,
                 cache: ComponentCache | None = None) -> None:
        self.config = config
        self.filter = SprintFilter(config, source, cache)
        self._obs = ObservationModel(config, sequence_first_of(source))
        self.frames: list[FrameBelief] = []

    def reset(self) -> None:
        """Start a new query sequence."""
        self.filter.reset()
        self._obs.reset()
        self.frames = []

    def set_novelty_dist(self, value: float | None) -> None:
        """The novelty distance for the next frames (:meth:`SprintFilter.set_novelty_dist`)."""
        self.filter.set_novelty_dist(value)
        self._obs.novelty_dist = value

    def forward(self, hit_ids: np.ndarray, hit_dists: np.ndarray,
                weights: np.ndarray | None = None, sink_weight: float = 1.0) -> None:
        """Filter one frame (as :meth:`SprintFilter.update`, with another cue's ``weights``
        and ``sink_weight`` if given) and keep its belief."""
        ids = np.asarray(hit_ids)
        vids, vdists, lik, sink_lik, _ = self._obs.evaluate(ids, np.asarray(hit_dists),
                                                            weights, sink_weight)
        self.filter.update_observed(vids, lik, sink_lik)  # a bad hit raises before any change
        ruled_out: frozenset[int] = frozenset()
        if weights is not None:
            low = np.asarray(weights).ravel() < RIVAL_MIN_WEIGHT
            ruled_out = frozenset(ids.ravel()[low].tolist())
        self.frames.append(FrameBelief.of_belief(self.filter.laid_belief(), vids,
                                                 [float(d) for d in vdists], lik, sink_lik,
                                                 ruled_out))

    def posteriors(self) -> list[tuple[list[tuple[ComponentTransition, np.ndarray, np.ndarray]],
                                       float]]:
        """The smoothed posterior of every frame: ``(parts, sink)`` like :class:`FrameBelief`
        (``parts``: transition, slots, gamma), in frame order."""
        out = [(self.frames[t].split(gamma), sink) for t, (gamma, sink)
               in zip(range(len(self.frames) - 1, -1, -1), self._backward(), strict=True)]
        out.reverse()
        return out

    def decisions(self) -> list[Decision]:
        """The decision of every frame from its smoothed posterior, in frame order.

        A match carries its ``contrast`` (:func:`~sprint_map.hmm.decision.place_contrast`
        over the frame's ``k`` nearest hits, as the causal filter reads them, whatever
        ``smooth_k`` the drive was searched with). Each frame's answer is reported on the
        drive the next frame's was, where the place holds it (``prefer_seq`` of
        :func:`decide_posterior`).
        """
        scratch = DecisionScratch()
        out: list[Decision] = []
        prefer: int | None = None
        # each frame's k nearest hits, read by its own contrast and its neighbours' (O(n k))
        nearest = [nearest_hits(frame, self.config.k) for frame in self.frames]
        for t, (gamma, sink) in zip(range(len(self.frames) - 1, -1, -1), self._backward(),
                                    strict=True):
            decision = decide_posterior(self.config, self.frames[t], gamma, sink, scratch,
                                        prefer, nearest, t)
            # Report a place by the drive the next frame was reported on, where it can be:
            # consecutive answers then follow one drive (see merge_rule's runs).
            if decision.candidate_id is not None and decision.seq_id is not None:
                prefer = decision.seq_id
            out.append(decision)
        out.reverse()
        return out

    def _backward(self) -> Iterable[tuple[np.ndarray, float]]:
        """Yield the smoothed posterior of each frame (:func:`gamma_of`), last frame first."""
        frames = self.frames
        if not frames:
            return
        last = frames[-1]
        beta = np.ones(last.starts()[-1])
        beta_sink = 1.0
        yield gamma_of(last, beta, beta_sink)
        bound = 1.0
        for t in range(len(frames) - 2, -1, -1):
            beta, beta_sink, bound = backward_step(self.config, frames[t], frames[t + 1], beta,
                                                   beta_sink, bound=bound)
            yield gamma_of(frames[t], beta, beta_sink)


_EMPTY_SLOTS = np.zeros(0, dtype=np.int64)
_MAX = np.maximum.reduce
_ADD = np.add.reduce
_EMPTY_VALS = np.zeros(0)


Parts = list[tuple[ComponentTransition, np.ndarray, np.ndarray]]


def backward_step(config: HMMConfig, now: FrameBelief, nxt: FrameBelief, beta: np.ndarray,
                  beta_sink: float, *, bound: float, keep: bool = False
                  ) -> tuple[np.ndarray, float, float]:
    """One step of the backward recursion: ``beta_t`` on the parts of frame ``now`` (laid end
    to end, :meth:`FrameBelief.starts`) from ``beta_{t+1}`` (``beta``, on the parts of ``nxt``
    laid end to end, and ``beta_sink``), both up to one positive factor (the posterior is
    normalised anyway).

    ``bound`` is an upper bound of ``beta`` and ``beta_sink`` (1 for a pass from ones); the
    step returns ``(beta_t, beta_sink_t, bound_t)``. The factor is left alone while the
    bound stays below :data:`RESCALE_ABOVE` and every value above ``RESCALE_BELOW`` (all of
    them are at least the restart term); past either, both are divided by their maximum.

    The step is linear in ``beta_{t+1}``: its operator (:func:`backward_operator`) is built from
    the two frames' supports and ``nxt``'s likelihoods; ``keep`` keeps it on ``now`` for the
    next step between the same frames (the fixed-lag smoother makes each step ``L`` times).

    Notes
    -----
    Building the operator is O(live W + live log live) for all the parts at once
    (:func:`~sprint_map.hmm.transition.parts_pull_operator`), what a forward step costs;
    applying it O(live W): one correlation over the parts' windows laid end to end. Nothing
    is sized by the map.
    """
    eps, nu = config.restart_prob, config.new_place_prob
    op = now.pulls
    if op is None:
        op = backward_operator(now, nxt)
        if keep:
            now.pulls = op
    # m_{t+1} = e_{t+1} * beta_{t+1} on the support of alpha_{t+1} (e is folded into op).
    m_sink = beta_sink * op.sink_lik
    if op.n_hits:
        hit_m = float(np.dot(op.hit_lik, beta[op.hit_pos])) if op.hit_pos.size else 0.0
        const = eps * hit_m / op.n_hits + nu * m_sink
    else:
        const = (eps + nu) * m_sink
    stay = 1.0 - eps - nu
    beta_sink = stay * m_sink + const
    new = op.pull.apply(beta, m_sink)
    new += const
    # every pulled value is a sum of A(u, j) e(j) m(j) whose weights sum to at most ``stay``
    bound = _SLACK * stay * max(op.lik_max * bound, m_sink) + const
    if bound > RESCALE_ABOVE or const < RESCALE_BELOW:
        top = max(float(_MAX(new)), beta_sink) if new.size else beta_sink
        if top > 0.0:
            inv = 1.0 / top
            new *= inv
            beta_sink *= inv
            bound = 1.0
    return new, beta_sink, bound


#: :func:`backward_step` rescales its values once an upper bound of them passes this ...
RESCALE_ABOVE = 1e100
#: ... or a lower bound falls below this.
RESCALE_BELOW = 1e-100
#: Room for rounding in :func:`backward_step`'s bound.
_SLACK = 1.0 + 1e-9


def backward_operator(now: FrameBelief, nxt: FrameBelief) -> BackwardOperator:
    """The backward step's operator from ``nxt`` onto ``now``: the pull of every part at once
    (:func:`~sprint_map.hmm.transition.parts_pull_operator`, each part's rows and columns
    where its values start, :meth:`FrameBelief.starts`), ``nxt``'s likelihood ratios folded
    into its targets; and ``nxt``'s hits, where its values laid end to end hold them.
    O(live W + live log live)."""
    space, comps = now.space()
    next_space, next_comps = nxt.space()  # (the same transitions, in order: the same space)
    pull = parts_pull_operator([(trans, slots) for trans, slots, _ in now.parts],
                               [(trans, slots) for trans, slots, _ in nxt.parts],
                               source_space=space,
                               target_space=next_space if next_comps == comps else None)
    hit_pos, hit_lik = nxt.held_hits()
    if hit_pos.size and pull.m_sel.size:
        e = np.ones(nxt.starts()[-1])
        e[hit_pos] = hit_lik
        pull.weigh_targets(e)
    # the largest likelihood ratio of a slot of ``nxt``: a hit's, or 1 (every other slot's)
    return BackwardOperator(pull, hit_pos, hit_lik, len(nxt.hit_ids),
                            max(1.0, max(nxt.hit_lik, default=1.0)), nxt.sink_lik)


class BackwardOperator:
    """What one backward step between two frames reads, built once (:func:`backward_operator`).

    Attributes
    ----------
    pull : PullOperator
        From the next frame's values (laid end to end) onto this frame's, the next frame's
        likelihood ratios folded in.
    hit_pos, hit_lik : ndarray
        The next frame's hits held by its values (positions laid end to end) and their
        likelihood ratios (the restart term's share of them).
    n_hits : int
        The next frame's distinct valid hits, held or not (the restart term's divisor).
    lik_max, sink_lik : float
        The next frame's largest likelihood ratio of a slot (its largest hit's, at least 1)
        and its sink's.
    """

    __slots__ = ("hit_lik", "hit_pos", "lik_max", "n_hits", "pull", "sink_lik")

    def __init__(self, pull: PullOperator, hit_pos: np.ndarray, hit_lik: np.ndarray,
                 n_hits: int, lik_max: float, sink_lik: float) -> None:
        self.pull, self.hit_pos, self.hit_lik = pull, hit_pos, hit_lik
        self.n_hits, self.lik_max, self.sink_lik = n_hits, lik_max, sink_lik


def gamma_of(frame: FrameBelief, beta: np.ndarray, beta_sink: float) -> tuple[np.ndarray, float]:
    """The smoothed posterior ``normalise(alpha_t * beta_t)`` of ``frame`` from ``beta_t``:
    gamma on its parts laid end to end (:meth:`FrameBelief.values`) and the sink's; the
    filtered one if the model gives the frames zero probability. O(live)."""
    gamma = frame.values() * beta
    sink = frame.sink * beta_sink
    total = sink + float(_ADD(gamma))
    if not total > 0.0 or not np.isfinite(total):
        # (Only if the model gives the whole drive zero probability: keep the filter's.)
        return frame.values(), frame.sink
    inv = 1.0 / total
    gamma *= inv
    return gamma, sink * inv


class DecisionScratch:
    """Dense slot vectors, one per component, that a smoothed posterior is written into for
    the decision code (zero between decisions), like the filter's own belief vectors."""

    def __init__(self) -> None:
        self.buffers: dict[int, np.ndarray] = {}

    def vector(self, trans: ComponentTransition) -> np.ndarray:
        key = trans.graph.component_id
        buf = self.buffers.get(key)
        if buf is None or len(buf) != trans.n_slots:
            if len(self.buffers) > 64:
                self.buffers.clear()
            buf = self.buffers[key] = np.zeros(trans.n_slots)
        return buf


def nearest_hits(frame: FrameBelief, k: int) -> tuple[list[int], list[float]]:
    """A frame's ``k`` nearest distinct hits (as the causal filter reads them, whatever
    ``smooth_k`` the drive was searched with), less those another cue ruled out
    (``ruled_out``: no rivals). O(k log k)."""
    ids, dists = frame.hit_ids, frame.hit_dists
    if len(ids) > k:
        if dists == sorted(dists):  # (as searched: sorted already)
            ids, dists = ids[:k], dists[:k]
        else:
            order = sorted(range(len(ids)), key=dists.__getitem__)[:k]
            ids, dists = [ids[i] for i in order], [dists[i] for i in order]
    if frame.ruled_out:
        keep = [i for i, v in enumerate(ids) if v not in frame.ruled_out]
        ids, dists = [ids[i] for i in keep], [dists[i] for i in keep]
    return ids, dists


def decide_posterior(config: HMMConfig, frame: FrameBelief, gamma: np.ndarray, sink: float,
                     scratch: DecisionScratch, prefer: int | None,
                     nearest: list[tuple[list[int], list[float]]], t: int) -> Decision:
    """The decision of frame ``t`` from its smoothed posterior (:func:`gamma_of`: ``gamma``
    on ``frame``'s parts laid end to end, and ``sink``).

    ``prefer`` is a sequence id to report the place by (:func:`decide`'s ``prefer_seq``);
    ``nearest`` holds the ``k`` nearest hits of the frames around ``t`` (``nearest[t]`` is
    frame ``t``'s; those of ``t - 2 .. t + 2`` that it holds confirm rivals), for the
    contrast of a match.

    Notes
    -----
    O(live) to find the candidates over all parts at once (:func:`top_positions`: what
    :func:`~sprint_map.hmm.decision.top_candidates` finds over one view per part), then
    O(live) to write the parts holding a candidate into ``scratch``, plus the place masses of
    the candidates and the contrast (:func:`place_contrast`).
    """
    starts = frame.starts()
    top = top_positions(gamma, config.decision_candidates)
    owner = [bisect_right(starts, pos) - 1 for _, pos in top]
    holding = sorted(set(owner))  # the parts holding a candidate, each one view
    views = []
    for i in holding:
        trans, slots, _ = frame.parts[i]
        buf = scratch.vector(trans)
        buf[slots] = gamma[starts[i]:starts[i + 1]]
        views.append(BeliefView(trans.graph, trans.slot_first, buf, idx=slots))
    view_of = {i: v for v, i in enumerate(holding)}
    candidates = [(p, view_of[i], int(frame.parts[i][1][pos - starts[i]]))
                  for (p, pos), i in zip(top, owner, strict=True)]

    def contrast_of(view: BeliefView, slot: int) -> float:
        ids, dists = nearest[t]
        return place_contrast(view, slot, ids, dists, config.place_radius, config.place_hops,
                              config.contrast_reach, ConfirmedRivals(t, nearest))

    decision = decide(views, candidates, sink, config.place_radius, config.place_hops,
                      config.min_confidence, len(frame.parts), starts[-1], prefer, contrast_of)
    for view in views:
        view.x[view.idx] = 0.0
    return decision


class ConfirmedRivals:
    """The hits of frame ``t`` that the frames around it confirm, as a container: ``h in
    rivals`` when at least :data:`RIVAL_CONFIRMATIONS` of the frames ``t - 2 .. t + 2`` have
    a hit (among their ``nearest``) within :data:`RIVAL_SLACK` images of where the same drive
    would be ``d`` frames away, ``h + d`` (vertex ids run along a sequence; near a sequence's
    end the next one may be counted: a rival too many, never one too few). A rival route, not
    a stray near neighbour.

    Notes
    -----
    O(k log k) to sort the neighbours' hits, then O(log k) per membership test (made only for
    the hits outside the decided place).
    """

    __slots__ = ("_around",)

    def __init__(self, t: int, nearest: list[tuple[list[int], list[float]]]) -> None:
        n = len(nearest)
        self._around = [(d, sorted(nearest[t + d][0])) for d in (-2, -1, 1, 2) if 0 <= t + d < n]

    def __contains__(self, h: object) -> bool:
        if not isinstance(h, int | np.integer):
            return False
        confirmations = 0
        for d, hits in self._around:
            at = int(h) + d
            i = bisect_left(hits, at - RIVAL_SLACK)
            if i < len(hits) and hits[i] <= at + RIVAL_SLACK:
                confirmations += 1
                if confirmations >= RIVAL_CONFIRMATIONS:
                    return True
        return False


def smooth(config: HMMConfig, source: GraphSource,
           hits: Iterable[tuple[np.ndarray, np.ndarray]],
           cache: ComponentCache | None = None) -> list[Decision]:
    """Smoothed decisions for a query sequence given each frame's ``(hit_ids, hit_dists)``.

    See :class:`ForwardBackward`.
    """
    fb = ForwardBackward(config, source, cache)
    for ids, dists in hits:
        fb.forward(ids, dists)
    return fb.decisions()
