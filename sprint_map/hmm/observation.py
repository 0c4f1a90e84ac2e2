"""Observation model: retrieval hits (vertex ids + squared-L2 distances) to likelihood ratios.

The likelihood is only ever used up to a constant factor (the belief is renormalised), so it is
expressed relative to an *unretrieved* vertex, whose ratio is 1. Then a frame touches only its
``k`` hits and the sink, never the rest of the map: the floor costs nothing.

For a frame with valid hits at distances ``d_1 <= ... <= d_far`` (padding ``-1`` ignored,
repeated ids keep their smallest distance) and kernel scale ``T``:

* hit ``i``: ``log L_i = (d_far - d_i) / T + miss_margin``. An unretrieved vertex is only known
  to be at least as far as ``d_far``; ``miss_margin`` is how much less likely it is than the
  farthest hit. This is the exponential kernel ``exp(-d / T)`` made relative to the frame.
* with ``rival_reach = R > 0`` (the *drive rival*, issue 51) and a source that tells each
  vertex's sequence: ``d_far`` in hit ``i``'s ratio becomes ``min(d_far, d_r)``, ``d_r`` the
  distance of the nearest other hit of the same sequence more than ``R`` images from it (among
  the frame's ``k`` nearest: a deep pass's rivals are the causal filter's), and the advantage
  is clipped at 0: ``log L_i = max(min(d_far, d_r) - d_i, 0) / T + miss_margin``.
  A drive near the frame everywhere (its condition, not the place) has such rivals and gains
  nothing over the farthest hit; a place's sharp minimum has none and keeps its ratio (SeqSLAM's
  local contrast, along the stored drive). O(k^2) more per frame, in numpy.
* sink ("off the map"): ``log L_s = novelty_margin``; if ``novelty_dist`` is set and
  ``d_1 > novelty_dist``, at least the value of a hit at ``novelty_dist``.
* a frame without valid hits carries no information: ``log L_s = 0`` like every vertex.
* another cue (GNSS, :mod:`sprint_map.localize.gnss`) may weigh the frame: each hit's ratio
  and the sink's are multiplied by the factors it gives (``weights``, ``sink_weight``; a
  repeated id keeps the factor of the entry kept), then clipped as above.

``T`` is ``dist_scale`` if set, else ``dist_scale_factor`` times an exponential moving average
(weight ``dist_scale_ema``) of the frames' spread ``d_far - d_1``: distances are then measured
in units of the descriptor's typical top-k spread, which makes the defaults work for descriptors
whose distances live on very different scales (HoG: spread ~0.03; patch-normalised: ~0.13). Log-ratios are clipped to
``[-200, 200]`` so that products stay finite in float64.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from sprint_map.hmm.config import HMMConfig

__all__ = ["Observation", "ObservationModel", "SequenceFirst", "sequence_first_of"]

#: Vertex ids (int64) -> the first vertex id of each one's sequence (a source's
#: ``sequence_first``): two hits are of one sequence iff these agree.
SequenceFirst = Callable[[np.ndarray], np.ndarray]


def sequence_first_of(source: Any) -> SequenceFirst | None:
    """``source.sequence_first`` if the graph source has one (the drive rival needs it), else
    None (the rival is then off)."""
    found = getattr(source, "sequence_first", None)
    return found if callable(found) else None

_CLIP = 200.0
_MIN_SCALE = 1e-12
_NDARRAY = np.ndarray
_ONE = (1,)


@dataclass(slots=True)
class Observation:
    """One frame's evidence.

    Attributes
    ----------
    vertex_ids : list of int
        Distinct valid hit vertex ids, in retrieval order.
    distances : list of float
        Their squared-L2 distances (clipped at 0).
    lik : list of float
        Likelihood ratio of each hit relative to an unretrieved vertex.
    sink_lik : float
        Likelihood ratio of the sink.
    scale : float
        The kernel scale ``T`` used (nan when it was not needed).
    """

    vertex_ids: list[int]
    distances: list[float]
    lik: list[float]
    sink_lik: float
    scale: float


class ObservationModel:
    """Turns retrieval hits into :class:`Observation` objects (stateful only through ``T``).

    Parameters
    ----------
    config : HMMConfig
    sequence_first : callable, optional
        Each vertex's sequence (:data:`SequenceFirst`), for ``config.rival_reach``; without it
        the rival is off.

    Notes
    -----
    :meth:`observe` is O(k) in pure Python after one conversion of each input array to a list,
    so it costs a few microseconds for k = 10.
    """

    __slots__ = ("_ema", "_factor", "_fixed", "_margin", "_novelty_dist", "_novelty_margin",
                 "_k", "_one_hit", "_plain", "_reach", "_scale", "_seq_first", "_sink_const")

    def __init__(self, config: HMMConfig, sequence_first: SequenceFirst | None = None) -> None:
        self._reach = config.rival_reach if sequence_first is not None else 0
        self._seq_first = sequence_first
        self._k = config.k
        self._fixed = config.dist_scale
        self._ema = config.dist_scale_ema
        self._factor = config.dist_scale_factor
        self._margin = config.miss_margin
        self._novelty_margin = config.novelty_margin
        self._novelty_dist = config.novelty_dist
        self._plain = config.novelty_dist is None  # the sink's ratio is a constant
        self._scale: float | None = None
        self._one_hit = math.exp(min(config.miss_margin, _CLIP))
        self._sink_const = math.exp(max(min(config.novelty_margin, _CLIP), -_CLIP))

    @property
    def scale(self) -> float | None:
        """Current kernel scale ``T`` (None while adaptive and no frame had two hits)."""
        if self._fixed is None and self._scale is None:
            return None
        return self._scale_now()

    @property
    def novelty_dist(self) -> float | None:
        """The absolute novelty distance in force (``HMMConfig.novelty_dist`` until set)."""
        return self._novelty_dist

    @novelty_dist.setter
    def novelty_dist(self, value: float | None) -> None:
        if value is not None and not (math.isfinite(value) and value >= 0.0):
            raise ValueError("novelty_dist must be a finite number >= 0 or None")
        self._novelty_dist = value
        self._plain = value is None

    def reset(self) -> None:
        """Forget the adaptive scale (start of a new query sequence)."""
        self._scale = None

    def observe(self, hit_ids: np.ndarray, hit_dists: np.ndarray) -> Observation:
        """Validate one frame's hits and compute their likelihood ratios.

        Parameters
        ----------
        hit_ids : array_like of int, shape (k,) or (1, k)
            Global vertex ids; ``-1`` is padding (ignored).
        hit_dists : array_like of float, same shape
            Squared-L2 distances (FAISS); ignored for padding. Tiny negative values (FAISS
            rounding) are clipped to 0.

        Raises
        ------
        ValueError
            On mismatched shapes, non-integer ids, an id below -1, or a non-finite distance of
            a valid hit.
        """
        return Observation(*self.evaluate(hit_ids, hit_dists))

    def single_hit(self, hit_ids: np.ndarray, hit_dists: np.ndarray) -> int:
        """The vertex id of a frame that is one plain hit, else -1 (then use :meth:`evaluate`).

        A plain hit: arrays of shape ``(1,)``, an integer id ``>= 0``, a finite distance
        ``>= 0``, and no ``novelty_dist``. Its likelihood ratio is :attr:`one_hit_lik` and the
        sink's is :attr:`sink_lik_const`, whatever the distance (a lone hit is its own
        farthest hit). This is the filters' k = 1 path (a vehicle's best match; the Fig. 4
        benchmark's): at a few µs per filter step, every operation of :meth:`evaluate` shows.
        """
        if (type(hit_ids) is _NDARRAY and type(hit_dists) is _NDARRAY and hit_ids.size == 1
                and hit_ids.ndim == 1 and hit_dists.shape == _ONE and self._plain):
            v = hit_ids.item()
            d = hit_dists.item()
            # (An integer array's item() is an int: that is the dtype check.)
            if type(v) is int and v >= 0 and 0.0 <= d < math.inf:
                return v
        return -1

    @property
    def one_hit_lik(self) -> float:
        """Likelihood ratio of the hit of a one-hit frame (``exp(miss_margin)``)."""
        return self._one_hit

    @property
    def sink_lik_const(self) -> float:
        """Likelihood ratio of the sink when ``novelty_dist`` is None (``exp(novelty_margin)``)."""
        return self._sink_const

    def evaluate(self, hit_ids: np.ndarray, hit_dists: np.ndarray,
                 weights: np.ndarray | None = None, sink_weight: float = 1.0
                 ) -> tuple[list[int], list[float], list[float], float, float]:
        """:meth:`observe` as a plain tuple ``(vertex_ids, distances, lik, sink_lik, scale)``.

        The filters' per-frame path uses this form: it skips building the dataclass.
        ``weights`` (one positive factor per entry of ``hit_ids``) and ``sink_weight`` are
        another cue's likelihood ratios, multiplied in (None and 1: none; O(k) more).
        """
        if weights is not None or sink_weight != 1.0:
            return self._weighted(hit_ids, hit_dists, weights, sink_weight)
        ids = hit_ids if type(hit_ids) is _NDARRAY else np.asarray(hit_ids)
        dists = hit_dists if type(hit_dists) is _NDARRAY else np.asarray(hit_dists)
        shape = ids.shape
        if shape != dists.shape or len(shape) > 2 or (len(shape) == 2 and shape[0] != 1):
            raise ValueError("hit_ids and hit_dists must have the same shape (k,) or (1, k)")
        if ids.dtype.kind not in "iu" and ids.size:
            raise ValueError("hit_ids must be integers")
        if len(shape) == 1:
            id_list = ids.tolist()
            d_list = dists.tolist()
        else:
            id_list = ids.ravel().tolist()
            d_list = dists.ravel().tolist()
        if len(id_list) == 1:
            # k = 1 in other forms (lists, (1, 1) arrays, a clipped distance) without the dict.
            v, d = id_list[0], d_list[0]
            if v >= 0 and math.isfinite(d):
                if d < 0.0:
                    d = 0.0
                if self._novelty_dist is None:
                    return [v], [d], [self._one_hit], self._sink_const, self._scale_now()
                scale = self._scale_now()
                return [v], [d], [self._one_hit], self._sink_lik(d, d, scale), scale
        if (len(id_list) > 8 and min(id_list) >= 0 and min(d_list) >= 0.0
                and math.isfinite(sum(d_list)) and len(set(id_list)) == len(id_list)):
            # distinct valid hits (what a search returns): the loop below would keep them all
            # (a NaN or an infinity makes the sum non-finite: the loop then raises)
            return self._liks(id_list, d_list)
        best: dict[int, float] = {}
        for v, d in zip(id_list, d_list, strict=True):
            if v < 0:
                if v != -1:
                    raise ValueError(f"invalid vertex id {v} (only -1 may pad)")
                continue
            if not math.isfinite(d):
                raise ValueError(f"distance of hit {v} is not finite")
            if d < 0.0:
                d = 0.0
            old = best.get(v)
            if old is None or d < old:
                best[v] = d
        if not best:
            return [], [], [], 1.0, math.nan
        return self._liks(list(best), list(best.values()))

    def _liks(self, vids: list[int], ds: list[float]
              ) -> tuple[list[int], list[float], list[float], float, float]:
        """:meth:`evaluate`'s answer for distinct valid hits ``vids`` at distances ``ds``
        (finite, >= 0): the likelihood ratios, after the distance scale's update."""
        d_far = max(ds)
        d_near = min(ds)
        if self._fixed is None and len(ds) > 1:
            gap = d_far - d_near
            self._scale = gap if self._scale is None else (
                self._scale + self._ema * (gap - self._scale))
        scale = self._scale_now()
        margin = self._margin
        if self._reach and len(ds) > 1:
            lik = self._rival_liks(vids, ds, d_far, scale)
        elif (d_far - d_near) / scale + margin <= _CLIP:  # the largest exponent: no clip needed
            lik = [math.exp((d_far - d) / scale + margin) for d in ds]
        else:
            lik = [math.exp(min((d_far - d) / scale + margin, _CLIP)) for d in ds]
        return vids, ds, lik, self._sink_lik(d_near, d_far, scale), scale

    def _rival_liks(self, vids: list[int], ds: list[float], d_far: float, scale: float
                    ) -> list[float]:
        """The likelihood ratios under the drive rival (module notes). O(k^2) in numpy."""
        assert self._seq_first is not None
        v = np.asarray(vids, dtype=np.int64)
        d = np.asarray(ds, dtype=np.float64)
        first = np.asarray(self._seq_first(v), dtype=np.int64)
        rivals = (first[:, None] == first[None, :]) & (np.abs(v[:, None] - v[None, :])
                                                        > self._reach)
        if len(d) > self._k:  # rivals among the frame's k nearest (a deep pass's 64 too)
            rivals &= (d <= np.partition(d, self._k - 1)[self._k - 1])[None, :]
        ref = np.minimum(np.where(rivals, d[None, :], d_far).min(axis=1), d_far)
        log = np.minimum(np.maximum(ref - d, 0.0) / scale + self._margin, _CLIP)
        out: list[float] = np.exp(log).tolist()
        return out

    def _weighted(self, hit_ids: np.ndarray, hit_dists: np.ndarray,
                  weights: np.ndarray | None, sink_weight: float
                  ) -> tuple[list[int], list[float], list[float], float, float]:
        """:meth:`evaluate` with another cue's factors multiplied in (see the module notes)."""
        vids, ds, lik, sink_lik, scale = self.evaluate(hit_ids, hit_dists)
        if not math.isfinite(sink_weight) or sink_weight <= 0.0:
            raise ValueError("sink_weight must be a finite number > 0")
        sink_lik = math.exp(max(min(math.log(sink_lik * sink_weight), _CLIP), -_CLIP))
        if weights is None or not vids:
            return vids, ds, lik, sink_lik, scale
        ids = np.asarray(hit_ids).ravel().tolist()
        w = np.asarray(weights, dtype=np.float64).ravel()
        if len(w) != len(ids) or not (np.isfinite(w) & (w > 0.0)).all():
            raise ValueError("weights must be one finite factor > 0 per hit")
        dists = np.asarray(hit_dists, dtype=np.float64).ravel().tolist()
        factor: dict[int, tuple[float, float]] = {}  # id -> (distance, weight) of the kept entry
        for v, d, f in zip(ids, dists, w.tolist(), strict=True):
            if v >= 0 and (v not in factor or d < factor[v][0]):
                factor[v] = (d, f)
        lik = [math.exp(max(min(math.log(x * factor[v][1]), _CLIP), -_CLIP))
               for v, x in zip(vids, lik, strict=True)]
        return vids, ds, lik, sink_lik, scale

    def _scale_now(self) -> float:
        if self._fixed is not None:
            return self._fixed
        # Before any frame with two hits no distance difference exists: T is irrelevant.
        return 1.0 if self._scale is None else max(self._scale * self._factor, _MIN_SCALE)

    def _sink_lik(self, d_near: float, d_far: float, scale: float) -> float:
        if self._novelty_dist is None:
            return self._sink_const
        log_sink = self._novelty_margin
        if self._novelty_dist is not None and d_near > self._novelty_dist:
            log_sink = max(log_sink, (d_far - self._novelty_dist) / scale + self._margin)
        return math.exp(max(min(log_sink, _CLIP), -_CLIP))
