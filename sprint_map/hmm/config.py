"""Parameters of the SPRINT hidden Markov model (``docs/hmm.md``, "The HMM")."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from sprint_map.util import dataclass_dict

__all__ = ["HMMConfig"]


@dataclass(frozen=True)
class HMMConfig:
    """Frozen parameters of the place-recognition HMM.

    Every open modelling choice of the filter is a field here; ``docs/hmm.md`` ("The
    model") gives the exact equations. Defaults were chosen by small grid searches on synthetic
    multi-traversal data and on Nordland summer -> winter HoG (``docs/hmm.md``,
    "HMMConfig"; figures in ``docs/benchmarks.md``, "HMM defaults: accuracy").

    Parameters
    ----------
    k : int
        Neighbours the caller retrieves per query frame (the filter accepts any number of hits;
        this is the facade's retrieval setting, kept here so a map remembers it).
    smooth_k : int
        Neighbours retrieved per frame when the drive is also smoothed (``ingest``,
        ``localize --smooth``, the service's sessions), if larger than ``k`` (0: ``k``). The
        causal filter still reads the ``k`` nearest. The smoothed decisions are made from the
        ``k`` nearest first (the merge rule and the unmapped place are tuned on that model),
        then again from all ``smooth_k``: over a whole drive, hits far down the list add
        evidence that consecutive frames confirm, so the deeper pass places more frames right
        under a change of conditions (Nordland winter -> summer smoothed recall@1 80.6 % at
        ``k`` 10, 86.2 % with 64), but it also keeps finding hits near one hypothesis on a
        street the map has never seen. So a frame the merge rule accepts keeps the ``k``-hit
        decision's acceptance, and every other frame answers with the deep decision, never
        merged (:meth:`sprint_map.localize.localizer.Localizer.smoothed`).
    window : tuple of float
        Forward transition window ``w``: ``w[0]`` is the weight of staying on the same image,
        ``w[i]`` of moving ``i`` images ahead in the same sequence. Normalised on use; never
        backwards. Mass that would move past the last image of a sequence goes to the sink. The
        default's mean advance is 1.13 images per frame (a query at the map's speed advances 1).
    edge_weight : float
        ``beta``: relative weight of following an inter-sequence edge versus staying in the own
        sequence. The row of a vertex ``u`` with out-edges ``u -> v_e`` (match probability
        ``c_e``) sends ``1 / R`` into its own window and ``beta * c_e / R`` into the window of
        ``v_e``, with ``R = 1 + beta * sum(c_e)``. 0 disables edges.
    prune_threshold : float
        Components whose share of the belief (sink included) falls below this after an update
        leave the active set; their belief is dropped and the rest renormalised (paper: 1e-4).
        0 disables pruning. With ``support_threshold`` also 0 the filter is exact w.r.t.
        :class:`FullGraphFilter`.
    max_active_components : int
        A beam over the active set: after pruning, only this many components (the most
        massive) stay active; the rest are pruned like those below ``prune_threshold``. It
        bounds a frame's cost where many unmerged drives of the same streets each receive a
        hit now and then (every drive its own component). 0: no beam.
    support_threshold : float
        Inside an active component only the *live support* is propagated: windows (runs of
        slots of one sequence) that hold belief. After each update, slots whose belief is below
        this share of the total (sink included) are trimmed from the ends of their window, and
        windows are split where at least ``W - 1`` consecutive slots are below it; the trimmed
        belief is dropped and the rest renormalised (like pruning, per slot). This is what makes
        the per-frame cost follow the belief rather than the component, which in a lifelong map
        grows into one giant component. 0 never trims: windows only grow (by ``W - 1`` per
        frame) and the filter stays exact.
    restart_prob : float
        ``epsilon``: prior mass re-injected each frame, uniformly over the frame's retrieval hits.
        This is what lets a hit start a new hypothesis (after a turn, a gap, a new place).
    new_place_prob : float
        ``nu``: prior mass moved each frame into the sink ("off the map": the vehicle left the
        mapped streets). Together with the sink's likelihood this is the novelty hypothesis.
    dist_scale : float or None
        ``T``: scale of the likelihood kernel, in squared-L2 distance units: a hit at distance
        ``d`` has log-likelihood ``(d_far - d) / T + miss_margin`` relative to an unretrieved
        vertex (``d_far``: the frame's largest hit distance). ``None`` (default) adapts ``T`` to
        the descriptor: ``dist_scale_factor`` times an exponential moving average of the frames'
        spread ``d_far - d_1``.
    dist_scale_ema : float
        Weight of the newest frame in that moving average (only used when ``dist_scale`` is
        None).
    dist_scale_factor : float
        The adaptive ``T`` is this times the moving average (only used when ``dist_scale`` is
        None).
    miss_margin : float
        Log-likelihood advantage of the farthest hit over an unretrieved vertex (which is only
        known to be at least as far as the farthest hit).
    novelty_margin : float
        Log-likelihood of the sink ("not any mapped place") relative to an unretrieved vertex.
        Between 0 and ``miss_margin`` the sink beats stale hypotheses that the retrieval no
        longer supports but loses to hypotheses that keep being retrieved.
    novelty_dist : float or None
        Optional absolute test: if the best hit of a frame is farther than this squared distance,
        the sink is scored like a hit at ``novelty_dist``, i.e. it explains the frame better than
        every hit. ``None`` (default) disables it (distances are descriptor-dependent).
    novelty_quantile : float
        Calibration of the unmapped-place hypothesis for smoothed (merge) decisions, per
        drive: after a first smoothing pass, the best-hit distances of the frames that are
        consistent matches (the map's merge rule without its lookalike tests: runs of 5
        frames, no contrast gate) are this drive's match distances to the map (under its own
        light and weather); their ``novelty_quantile`` quantile becomes ``novelty_dist`` for a
        second pass, so a frame whose best hit is farther than the drive's matches
        is explained at least as well by an unmapped place. 0 disables it (and so does a
        ``novelty_dist`` set by hand). The causal filter does not use it.
    novelty_window : int
        The calibration is local: frame ``t`` uses the matched frames within this many
        frames of it (light and weather change along a drive: tunnels, dusk), or the whole
        drive where fewer than 10 lie that close. 0: the whole drive.
    place_radius : int
        ``r``: a place is the vertex's temporal neighbourhood ``[i - r, i + r]`` in its sequence
        plus the same neighbourhood of every vertex reached from that neighbourhood over at most
        ``place_hops`` edges (either direction). The decision's ``prob`` is the belief mass of
        the place.
    place_hops : int
        ``h``: how many edges a place reaches across (drives chained by merge edges: one hop
        per drive in the chain). 0 limits a place to one sequence.
    contrast_reach : int
        Smoothed decisions report a *contrast* (:func:`sprint_map.hmm.decision.place_contrast`):
        the frame's best hit inside the decided place over its best hit elsewhere, where
        "elsewhere" excludes the place's surroundings, this many images around it (the same
        road a few images on is not a rival place). The merge rule reads it
        (``MapConfig.merge_max_contrast``).
    decision_candidates : int
        How many of the most probable vertices are scored by place mass; the decision is the
        candidate whose place holds the most mass.
    min_confidence : float
        A decision whose place mass is below this is reported as "no match".
    cache_budget_bytes : int
        Byte budget of the LRU component cache (:class:`sprint_map.hmm.cache.ComponentCache`).
    """

    k: int = 10
    smooth_k: int = 64
    window: tuple[float, ...] = (0.25, 0.5, 0.15, 0.07, 0.03)
    edge_weight: float = 1.0
    prune_threshold: float = 1e-4
    max_active_components: int = 8
    support_threshold: float = 1e-6
    restart_prob: float = 0.01
    new_place_prob: float = 0.01
    dist_scale: float | None = None
    dist_scale_ema: float = 0.05
    dist_scale_factor: float = 0.5
    miss_margin: float = 1.0
    novelty_margin: float = 0.25
    novelty_dist: float | None = None
    novelty_quantile: float = 0.85
    novelty_window: int = 100
    place_radius: int = 2
    place_hops: int = 4
    contrast_reach: int = 20
    decision_candidates: int = 4
    min_confidence: float = 0.2
    cache_budget_bytes: int = 256 << 20

    def __post_init__(self) -> None:
        if not _is_int(self.k) or self.k < 1:
            raise ValueError("k must be an integer >= 1")
        if not _is_int(self.smooth_k) or self.smooth_k < 0:
            raise ValueError("smooth_k must be an integer >= 0")
        window = tuple(float(w) for w in self.window)
        if not window or not all(math.isfinite(w) and w >= 0 for w in window) or sum(window) <= 0:
            raise ValueError("window must be non-empty, finite, non-negative and not all zero")
        object.__setattr__(self, "window", window)
        _finite_range("edge_weight", self.edge_weight, 0.0, math.inf)
        _finite_range("prune_threshold", self.prune_threshold, 0.0, 1.0, hi_open=True)
        if not _is_int(self.max_active_components) or self.max_active_components < 0:
            raise ValueError("max_active_components must be an integer >= 0")
        _finite_range("support_threshold", self.support_threshold, 0.0, 1.0, hi_open=True)
        _finite_range("restart_prob", self.restart_prob, 0.0, 1.0)
        _finite_range("new_place_prob", self.new_place_prob, 0.0, 1.0)
        if self.restart_prob + self.new_place_prob >= 1:
            raise ValueError("restart_prob + new_place_prob must be < 1")
        if self.dist_scale is not None:
            _finite_range("dist_scale", self.dist_scale, 0.0, math.inf, lo_open=True)
        _finite_range("dist_scale_ema", self.dist_scale_ema, 0.0, 1.0, lo_open=True)
        _finite_range("dist_scale_factor", self.dist_scale_factor, 0.0, math.inf, lo_open=True)
        _finite_range("miss_margin", self.miss_margin, 0.0, 700.0)
        _finite_range("novelty_margin", self.novelty_margin, -700.0, 700.0)
        if self.novelty_dist is not None:
            _finite_range("novelty_dist", self.novelty_dist, 0.0, math.inf)
        _finite_range("novelty_quantile", self.novelty_quantile, 0.0, 1.0)
        if not _is_int(self.novelty_window) or self.novelty_window < 0:
            raise ValueError("novelty_window must be an integer >= 0")
        if not _is_int(self.place_radius) or self.place_radius < 0:
            raise ValueError("place_radius must be an integer >= 0")
        if not _is_int(self.place_hops) or self.place_hops < 0:
            raise ValueError("place_hops must be an integer >= 0")
        if not _is_int(self.contrast_reach) or self.contrast_reach < 0:
            raise ValueError("contrast_reach must be an integer >= 0")
        if not _is_int(self.decision_candidates) or self.decision_candidates < 1:
            raise ValueError("decision_candidates must be an integer >= 1")
        _finite_range("min_confidence", self.min_confidence, 0.0, 1.0)
        if not _is_int(self.cache_budget_bytes) or self.cache_budget_bytes < 0:
            raise ValueError("cache_budget_bytes must be an integer >= 0")

    @property
    def window_len(self) -> int:
        """``W``, the number of window weights."""
        return len(self.window)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> HMMConfig:
        """Build from a dict (as stored in the map's meta record)."""
        return dataclass_dict.from_dict(cls, data)

    def to_dict(self) -> dict[str, Any]:
        """Return a JSON-ready dict."""
        return dataclass_dict.to_dict(self)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _finite_range(name: str, value: Any, lo: float, hi: float, *, lo_open: bool = False,
                  hi_open: bool = False) -> None:
    """Raise ValueError unless ``value`` is a real number in the given range."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number")
    if value < lo or (lo_open and value == lo) or value > hi or (hi_open and value == hi):
        left = "(" if lo_open else "["
        right = ")" if hi_open else "]"
        raise ValueError(f"{name} must be in {left}{lo}, {hi}{right}")
