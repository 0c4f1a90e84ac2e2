"""Parameters of the SPRINT hidden Markov model (``docs/hmm.md``, "The HMM")."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from sprint_map.util import dataclass_dict
from sprint_map.util.dataclass_dict import check_int, check_number

__all__ = ["HMMConfig"]


@dataclass(frozen=True)
class HMMConfig:
    """Frozen parameters of the place-recognition HMM, one field per open modelling choice.

    ``docs/hmm.md`` ("The model") gives the equations each field enters; every field is
    described by the comment above it. Validated on construction (``ValueError``); O(1).
    Why the defaults are what they are: ``docs/decisions.md`` ("The HMM").
    """

    #: Neighbours the caller retrieves per query frame (the facade's retrieval setting, kept
    #: here so a map remembers it; the filter accepts any number of hits).
    k: int = 10
    #: Neighbours retrieved per frame when the drive is also smoothed (``ingest``, ``localize
    #: --smooth``, the service's sessions), if larger than ``k`` (0: ``k``): the *deep pass*.
    #: Frames the merge rule accepts keep the ``k``-hit decision; every other frame answers
    #: with the deep decision, never merged. The causal filter reads the ``k`` nearest only.
    smooth_k: int = 64
    #: Forward transition window ``w``: ``w[0]`` weighs staying on the same image, ``w[i]``
    #: moving ``i`` images ahead in the same sequence. Normalised on use; never backwards; mass
    #: past a sequence's last image goes to the sink. Default mean advance: 1.13 images/frame.
    window: tuple[float, ...] = (0.25, 0.5, 0.15, 0.07, 0.03)
    #: ``beta``: weight of following an inter-sequence edge against staying in the sequence.
    #: A vertex ``u`` with out-edges ``u -> v_e`` (match probability ``c_e``) sends ``1 / R``
    #: into its own window and ``beta * c_e / R`` into ``v_e``'s, ``R = 1 + beta * sum(c_e)``.
    #: 0 disables edges.
    edge_weight: float = 1.0
    #: Components whose share of the belief (sink included) falls below this leave the active
    #: set, their belief dropped and the rest renormalised (paper: 1e-4). 0: no pruning; with
    #: ``support_threshold`` also 0 the filter equals :class:`FullGraphFilter` exactly.
    prune_threshold: float = 1e-4
    #: A beam over the active set: only this many components (the most massive) stay active
    #: after pruning; it bounds a frame's cost when many unmerged drives of the same streets
    #: each get a hit now and then. 0: no beam.
    max_active_components: int = 8
    #: The *live support*: slots below this share of the belief are trimmed from the ends of
    #: their window, and windows split where ``W - 1`` consecutive slots are below it (the
    #: trimmed belief dropped, the rest renormalised), so a frame's cost follows the belief,
    #: not the component. 0: never trim (windows grow by ``W - 1`` a frame; exact).
    support_threshold: float = 1e-6
    #: ``epsilon``: prior mass re-injected each frame uniformly over the frame's retrieval
    #: hits; what lets a hit start a new hypothesis (after a turn, a gap, a new place).
    restart_prob: float = 0.01
    #: ``nu``: prior mass moved each frame into the sink ("off the map"). With the sink's
    #: likelihood this is the novelty hypothesis.
    new_place_prob: float = 0.01
    #: ``T``: scale of the likelihood kernel in squared-L2 units: a hit at distance ``d`` has
    #: log-likelihood ``(d_far - d) / T + miss_margin`` over an unretrieved vertex (``d_far``:
    #: the frame's farthest hit). ``None``: ``dist_scale_factor`` times a moving average of
    #: the frames' spread ``d_far - d_1``.
    dist_scale: float | None = None
    #: Weight of the newest frame in that moving average (``dist_scale`` None only).
    dist_scale_ema: float = 0.05
    #: The adaptive ``T`` is this times the moving average (``dist_scale`` None only).
    dist_scale_factor: float = 0.5
    #: Log-likelihood advantage of the farthest hit over an unretrieved vertex.
    miss_margin: float = 1.0
    #: The *drive rival* (issue 51; 0: off): a hit's advantage is measured from the nearer of
    #: ``d_far`` and its drive's closest other hit (among the ``k`` nearest) more than this many
    #: images away, so a drive close to the frame everywhere (its condition) gains nothing.
    #: Off: on the Nordland pair it costs merge precision (``docs/decisions.md``, "Front end").
    rival_reach: int = 0
    #: Log-likelihood of the sink over an unretrieved vertex. Between 0 and ``miss_margin`` the
    #: sink beats stale hypotheses the retrieval no longer supports, not retrieved ones.
    novelty_margin: float = 0.25
    #: If a frame's best hit is farther than this squared distance, the sink scores like a hit
    #: at ``novelty_dist`` (it explains the frame better than every hit). ``None``: off.
    novelty_dist: float | None = None
    #: The calibrated *unmapped place* of smoothed decisions: after a first smoothing pass, the
    #: best-hit distances of the drive's consistent matches (runs of 5 frames, no contrast
    #: gate) are its match distances; their ``novelty_quantile`` quantile becomes
    #: ``novelty_dist`` for a second pass. 0 (or a ``novelty_dist`` set by hand): off.
    novelty_quantile: float = 0.85
    #: The calibration is local: frame ``t`` uses the matched frames within this many frames
    #: (or the whole drive where fewer than 10 lie that close). 0: the whole drive.
    novelty_window: int = 100
    #: ``r``: a place is the vertex's neighbourhood ``[i - r, i + r]`` in its sequence plus the
    #: same of every vertex reached over at most ``place_hops`` edges (either direction); a
    #: decision's ``prob`` is the place's belief mass.
    place_radius: int = 2
    #: ``h``: how many edges a place reaches across (one hop per drive in a chain of merges).
    #: 0 limits a place to one sequence.
    place_hops: int = 4
    #: The *contrast* of smoothed decisions (:func:`sprint_map.hmm.decision.place_contrast`)
    #: compares the best hit inside the place with the best elsewhere, excluding this many
    #: images around the place (the same road a few images on is no rival). The merge rule
    #: reads it (``merge_max_contrast``).
    contrast_reach: int = 20
    #: How many of the most probable vertices are scored by place mass; the decision is the
    #: candidate whose place holds the most.
    decision_candidates: int = 4
    #: A decision whose place mass is below this is reported as "no match".
    min_confidence: float = 0.2
    #: Byte budget of the LRU component cache (:class:`sprint_map.hmm.cache.ComponentCache`).
    cache_budget_bytes: int = 256 << 20

    def __post_init__(self) -> None:
        check_int("k", self.k, 1)
        check_int("smooth_k", self.smooth_k, 0)
        window = tuple(float(w) for w in self.window)
        if not window or not all(math.isfinite(w) and w >= 0 for w in window) or sum(window) <= 0:
            raise ValueError("window must be non-empty, finite, non-negative and not all zero")
        object.__setattr__(self, "window", window)
        check_number("edge_weight", self.edge_weight, 0.0, math.inf)
        check_number("prune_threshold", self.prune_threshold, 0.0, 1.0, hi_open=True)
        check_int("max_active_components", self.max_active_components, 0)
        check_number("support_threshold", self.support_threshold, 0.0, 1.0, hi_open=True)
        check_number("restart_prob", self.restart_prob, 0.0, 1.0)
        check_number("new_place_prob", self.new_place_prob, 0.0, 1.0)
        if self.restart_prob + self.new_place_prob >= 1:
            raise ValueError("restart_prob + new_place_prob must be < 1")
        if self.dist_scale is not None:
            check_number("dist_scale", self.dist_scale, 0.0, math.inf, lo_open=True)
        check_number("dist_scale_ema", self.dist_scale_ema, 0.0, 1.0, lo_open=True)
        check_number("dist_scale_factor", self.dist_scale_factor, 0.0, math.inf, lo_open=True)
        check_number("miss_margin", self.miss_margin, 0.0, 700.0)
        check_int("rival_reach", self.rival_reach, 0)
        check_number("novelty_margin", self.novelty_margin, -700.0, 700.0)
        if self.novelty_dist is not None:
            check_number("novelty_dist", self.novelty_dist, 0.0, math.inf)
        check_number("novelty_quantile", self.novelty_quantile, 0.0, 1.0)
        check_int("novelty_window", self.novelty_window, 0)
        check_int("place_radius", self.place_radius, 0)
        check_int("place_hops", self.place_hops, 0)
        check_int("contrast_reach", self.contrast_reach, 0)
        check_int("decision_candidates", self.decision_candidates, 1)
        check_number("min_confidence", self.min_confidence, 0.0, 1.0)
        check_int("cache_budget_bytes", self.cache_budget_bytes, 0)

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
