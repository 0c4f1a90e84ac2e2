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

import math
from collections.abc import Iterable
from dataclasses import dataclass, replace

import numpy as np

from sprint_map.hmm.cache import ComponentCache
from sprint_map.hmm.config import HMMConfig
from sprint_map.hmm.decision import BeliefView, Decision, decide, place_contrast, top_candidates
from sprint_map.hmm.graph import GraphSource
from sprint_map.hmm.observation import ObservationModel
from sprint_map.hmm.sprint_filter import SprintFilter
from sprint_map.hmm.transition import ComponentTransition

__all__ = ["FrameBelief", "ForwardBackward", "RIVAL_CONFIRMATIONS", "RIVAL_MIN_WEIGHT",
           "RIVAL_SLACK", "smooth"]

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


class ForwardBackward:
    """Smoothed decisions for a whole query sequence over a :class:`GraphSource`.

    Parameters
    ----------
    config : HMMConfig
    source : GraphSource
    cache : ComponentCache, optional
        Shared component cache (e.g. the causal localizer's).

    Notes
    -----
    :meth:`forward` costs one filter step per frame plus O(live) to keep its belief; the
    backward pass costs the same per frame (:meth:`ComponentTransition.pull`) plus one
    decision. Nothing is sized by the map.

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
        self._obs = ObservationModel(config)
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
        dists = np.asarray(hit_dists)
        self.filter.update(ids, dists, weights, sink_weight)  # validates the hits first
        vids, vdists, lik, sink_lik, _ = self._obs.evaluate(ids, dists, weights, sink_weight)
        parts, sink = self.filter.live_belief()
        ruled_out: frozenset[int] = frozenset()
        if weights is not None:
            low = np.asarray(weights).ravel() < RIVAL_MIN_WEIGHT
            ruled_out = frozenset(ids.ravel()[low].tolist())
        self.frames.append(FrameBelief(parts, sink, vids, [float(d) for d in vdists], lik,
                                       sink_lik, ruled_out))

    def posteriors(self) -> list[tuple[list[tuple[ComponentTransition, np.ndarray, np.ndarray]],
                                       float]]:
        """The smoothed posterior of every frame: ``(parts, sink)`` like :class:`FrameBelief`
        (``parts``: transition, slots, gamma), in frame order."""
        out = []
        for parts, sink in self._backward():
            out.append((parts, sink))
        out.reverse()
        return out

    def decisions(self) -> list[Decision]:
        """The decision of every frame from its smoothed posterior, in frame order.

        A match carries its ``contrast`` (:func:`~sprint_map.hmm.decision.place_contrast`
        over the frame's ``k`` nearest hits, as the causal filter reads them, whatever
        ``smooth_k`` the drive was searched with).
        """
        cfg = self.config
        buffers: dict[int, np.ndarray] = {}
        out: list[Decision] = []
        prefer: int | None = None
        # each frame's k nearest hits, read by its own contrast and its neighbours' (O(n k))
        nearest = [self._nearest_hits(t) for t in range(len(self.frames))]
        for t, (parts, sink) in zip(range(len(self.frames) - 1, -1, -1), self._backward(),
                                    strict=True):
            views = []
            for trans, slots, gamma in parts:
                key = trans.graph.component_id
                buf = buffers.get(key)
                if buf is None:
                    if len(buffers) > 64:
                        buffers.clear()
                    buf = buffers[key] = np.zeros(trans.n_slots)
                buf[slots] = gamma
                views.append(BeliefView(trans.graph, trans.slot_first, buf, idx=slots))
            candidates = top_candidates(views, cfg.decision_candidates)
            n_vertices = sum(len(slots) for _, slots, _ in parts)
            decision = decide(views, candidates, sink, cfg.place_radius, cfg.place_hops,
                              cfg.min_confidence, len(parts), n_vertices, prefer)
            # Report a place by the drive the next frame was reported on, where it can be:
            # consecutive answers then follow one drive (see merge_rule's runs).
            if decision.candidate_id is not None and decision.seq_id is not None:
                prefer = decision.seq_id
            if decision.vertex_id is not None:
                decision = replace(decision, contrast=self._contrast(views, decision.vertex_id,
                                                                     t, nearest))
            out.append(decision)
            for (_, slots, _), view in zip(parts, views, strict=True):
                view.x[slots] = 0.0
        out.reverse()
        return out

    def _contrast(self, views: list[BeliefView], vertex_id: int, t: int,
                  nearest: list[tuple[list[int], list[float]]]) -> float:
        cfg = self.config
        ids, dists = nearest[t]
        for view in views:
            s = int(view.graph.seq_index(np.array([vertex_id]))[0])
            if s >= 0:
                slot = int(view.slot_first[s]) + vertex_id - int(view.graph.seq_first[s])
                return place_contrast(view, slot, ids, dists, cfg.place_radius,
                                      cfg.place_hops, cfg.contrast_reach,
                                      _confirmed(ids, t, nearest))
        return math.nan  # not reached: the decided vertex lies in one of the views

    def _nearest_hits(self, t: int) -> tuple[list[int], list[float]]:
        """Frame ``t``'s ``k`` nearest distinct hits (as the causal filter reads them, whatever
        ``smooth_k`` the drive was searched with), less those another cue ruled out."""
        frame = self.frames[t]
        ids, dists = frame.hit_ids, frame.hit_dists
        if len(ids) > self.config.k:
            order = sorted(range(len(ids)), key=dists.__getitem__)[:self.config.k]
            ids, dists = [ids[i] for i in order], [dists[i] for i in order]
        if frame.ruled_out:
            keep = [i for i, v in enumerate(ids) if v not in frame.ruled_out]
            ids, dists = [ids[i] for i in keep], [dists[i] for i in keep]
        return ids, dists

    def _backward(self) -> Iterable[tuple[list[tuple[ComponentTransition, np.ndarray,
                                                     np.ndarray]], float]]:
        """Yield the smoothed posterior of each frame, last frame first."""
        frames = self.frames
        if not frames:
            return
        cfg = self.config
        eps, nu = cfg.restart_prob, cfg.new_place_prob
        scale = 1.0 - eps - nu
        last = frames[-1]
        betas = [np.ones(len(slots)) for _, slots, _ in last.parts]
        beta_sink = 1.0
        yield self._gamma(last, betas, beta_sink)
        for t in range(len(frames) - 2, -1, -1):
            now, nxt = frames[t], frames[t + 1]
            # m_{t+1} = e_{t+1} * beta_{t+1} on the support of alpha_{t+1}.
            m_by_trans: dict[int, tuple[np.ndarray, np.ndarray]] = {}
            hit_m = 0.0
            lik_of = dict(zip(nxt.hit_ids, nxt.hit_lik, strict=True))
            for (trans, slots, _), beta in zip(nxt.parts, betas, strict=True):
                m = beta.copy()
                if lik_of:
                    vids = trans.vertex_of_slots(slots) if slots.size else slots
                    for i, v in enumerate(vids.tolist()):
                        lik = lik_of.get(v)
                        if lik is not None:
                            m[i] *= lik
                            hit_m += m.item(i)
                m_by_trans[trans.graph.component_id] = (slots, m)
            m_sink = beta_sink * nxt.sink_lik
            n_hits = len(nxt.hit_ids)
            const = (eps * hit_m / n_hits + nu * m_sink) if n_hits else (eps + nu) * m_sink
            new_betas = []
            for trans, slots, _ in now.parts:
                m_slots, m_vals = m_by_trans.get(trans.graph.component_id,
                                                 (_EMPTY_SLOTS, _EMPTY_VALS))
                new_betas.append(trans.pull(slots, m_slots, m_vals, m_sink) + const)
            beta_sink = scale * m_sink + const
            # Rescale (gamma is normalised anyway): keep beta near 1.
            top = max([beta_sink] + [float(b.max()) for b in new_betas if b.size])
            if top > 0.0:
                new_betas = [b / top for b in new_betas]
                beta_sink /= top
            betas = new_betas
            yield self._gamma(now, betas, beta_sink)

    @staticmethod
    def _gamma(frame: FrameBelief, betas: list[np.ndarray], beta_sink: float
               ) -> tuple[list[tuple[ComponentTransition, np.ndarray, np.ndarray]], float]:
        parts = [(trans, slots, alpha * beta)
                 for (trans, slots, alpha), beta in zip(frame.parts, betas, strict=True)]
        sink = frame.sink * beta_sink
        total = sink + sum(float(g.sum()) for _, _, g in parts)
        if not total > 0.0 or not np.isfinite(total):
            # (Only if the model gives the whole drive zero probability: keep the filter's.)
            return list(frame.parts), frame.sink
        inv = 1.0 / total
        return [(t, s, g * inv) for t, s, g in parts], sink * inv


_EMPTY_SLOTS = np.zeros(0, dtype=np.int64)
_EMPTY_VALS = np.zeros(0)


def _confirmed(ids: list[int], t: int, nearest: list[tuple[list[int], list[float]]]
               ) -> set[int]:
    """The hits ``ids`` of frame ``t`` that the frames around it confirm: at least
    :data:`RIVAL_CONFIRMATIONS` of the frames ``t - 2 .. t + 2`` have a hit (among their
    ``nearest``) within :data:`RIVAL_SLACK` images of where the same drive would be ``d``
    frames away (vertex ids run along a sequence; near a sequence's end the next one may be
    counted: a rival too many, never one too few). A rival route, not a stray near neighbour.
    O(k^2)."""
    n = len(nearest)
    near = [(d, nearest[t + d][0]) for d in (-2, -1, 1, 2) if 0 <= t + d < n]
    out = set()
    for h in ids:
        votes = sum(1 for d, other in near
                    if any(abs(w - (h + d)) <= RIVAL_SLACK for w in other))
        if votes >= RIVAL_CONFIRMATIONS:
            out.add(h)
    return out


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
