"""GNSS as an optional cue: a drive's fixes against the positions the map stores.

When a drive carries fixes (``x, y`` metres in the map's planar frame, optionally each with
its accuracy ``sigma_m``; NaN: a frame without a fix) and the map stores positions of its
vertices, each frame with a fix is weighed by where it is (``docs/hmm.md``, "GNSS"):

* the **gate** of a fix and a mapped position is
  ``max(gate_m, n_sigma * sqrt(sigma_fix^2 + sigma_map^2))``: farther apart, the two cannot be
  the same place (beyond the receivers' accuracy and a slow drift of both);
* the **direction of travel** of a frame is read from its drive's track (the fixes, or the
  positions the map stores, ``HEADING_HALF`` frames either side; unknown over less than
  ``HEADING_MIN_SPAN_M``): a place whose mapped direction differs from the frame's by more than
  ``heading_gate_deg`` is not where the vehicle is either (a street driven the other way, a
  crossing street at an intersection), however near;
* (a) a decision whose place lies beyond the gate of the frame's fix (or against its
  direction) is marked ``confirmed=False``: answered, never merged
  (:mod:`sprint_map.merge.rule`);
* (b) the ``max_added`` map vertices nearest the fix inside the gate (the nearest of each
  sequence there first, then the second nearest of each, ...) join the frame's retrieval hits,
  at the distance of its farthest hit, so a retrieval miss near a good fix can still be
  recovered;
* every hit is weighed by ``w(d) = exp(-min(far_log_cap, ((d - gate) / sigma)^2 / 2))`` for
  its distance ``d`` to the fix beyond the gate (1 inside), ``sigma`` the two accuracies
  combined, and by ``exp(-far_log_cap)`` against the frame's direction: a hit on a lookalike
  (or an identical twin) street elsewhere loses to the place where the vehicle is; the cap
  bounds what one wrong fix can veto;
* (c) the unmapped place's likelihood is divided by ``w`` of the nearest mapped position when
  every hit of the frame has a position: a fix far from every mapped place raises
  ``novel_prob``.

A fix that disagrees with the drive's own track (farther than ``max(gate_m, 1.5 sigma)`` from
the median of the drive's fixes within ``consistency_window`` frames either side: a multipath
jump) is dropped, as if the frame had none. A frame without a fix, a hit without a position,
a drive without fixes: nothing changes.
The spatial look-ups go through a KD-tree of the map's positions (:class:`PositionIndex`), built
once per map snapshot, O(log n) per frame. A mapped frame without a fix between two with one
(a tunnel of a mapped drive) is placed on the line between them, its accuracy widened by a
quarter of their distance: the drive went from one to the other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sprint_map.errors import InputError
from sprint_map.util.arrays import Float64Array
from sprint_map.util.dataclass_dict import check_int

__all__ = ["HEADING_HALF", "HEADING_MIN_SPAN_M", "MAX_COORD_M", "GnssAid", "GnssConfig", "PositionIndex", "consistent", "validate_fixes"]

#: Planar coordinates beyond this many metres lie on no map of the Earth: a bad fix.
MAX_COORD_M = 1e8
#: Nearest mapped vertices read per look-up, before one per sequence is kept.
_QUERY_K = 32
#: A frame's direction of travel: from its track this many frames before to as many after...
HEADING_HALF = 4
#: ... when those lie at least this many metres apart (else unknown).
HEADING_MIN_SPAN_M = 10.0


@dataclass(frozen=True)
class GnssConfig:
    """How GNSS fixes weigh localisation and merging (:mod:`sprint_map.localize.gnss`); each
    field is documented by its ``#:`` comment (``docs/hmm.md``, "GNSS")."""

    #: Accuracy (one standard deviation, metres) of a drive's fix that gives none.
    sigma_m: float = 10.0
    #: Accuracy of a position the map stores without one.
    map_sigma_m: float = 10.0
    #: The smallest gate (metres): fix and place farther apart are not the same place.
    gate_m: float = 25.0
    #: The gate in combined standard deviations, where that is larger than ``gate_m``.
    n_sigma: float = 3.0
    #: Map vertices near the fix that join a frame's hits (0: none).
    max_added: int = 4
    #: The most a fix may lower a hit's log-likelihood (and raise the unmapped place's).
    far_log_cap: float = 8.0
    #: Log-weight of a vertex added near the fix, over the farthest hit's likelihood (-1
    #: cancels the default ``miss_margin``: the added vertex gets the restart mass a hit gets,
    #: not a hit's evidence).
    added_log_weight: float = -1.0
    #: Frames either side of a fix its drive's track is read over (0: every fix is kept).
    consistency_window: int = 8
    #: Largest difference (degrees) between a frame's direction of travel and its place's
    #: (both from their tracks) for the place to be where the vehicle is (180: any).
    heading_gate_deg: float = 45.0
    #: Along a drive's decisions on one sequence, the offset from each fix to its place's
    #: mapped position drifts slowly (both drifts do); a decision whose offset lies farther
    #: than this from the median offset of those within ``consistency_window`` frames is not
    #: confirmed (a place stuck while the drive moves on; 0: off).
    offset_m: float = 20.0

    def __post_init__(self) -> None:
        for name in ("sigma_m", "map_sigma_m", "gate_m", "n_sigma", "far_log_cap"):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a finite number > 0")
        check_int("max_added", self.max_added, 0)
        if not (isinstance(self.added_log_weight, int | float)
                and -self.far_log_cap <= self.added_log_weight <= 0):
            raise ValueError("added_log_weight must be in [-far_log_cap, 0]")
        check_int("consistency_window", self.consistency_window, 0)
        if not (math.isfinite(self.offset_m) and self.offset_m >= 0):
            raise ValueError("offset_m must be a finite number >= 0")
        if not 0 < self.heading_gate_deg <= 180:
            raise ValueError("heading_gate_deg must be in (0, 180]")

    def gate(self, sigma_fix: Any, sigma_map: Any) -> Any:
        """The gate (metres) of fixes of these accuracies (arrays broadcast). O(size)."""
        return np.maximum(self.gate_m, self.n_sigma * np.hypot(sigma_fix, sigma_map))

    def weight(self, dist: Any, sigma_fix: Any, sigma_map: Any) -> Any:
        """``w(d)`` of the module notes: 1 inside the gate, falling beyond it. O(size)."""
        sigma = np.hypot(sigma_fix, sigma_map)
        beyond = np.maximum(np.asarray(dist, dtype=np.float64) - self.gate(sigma_fix, sigma_map),
                            0.0) / sigma
        return np.exp(-np.minimum(self.far_log_cap, 0.5 * beyond * beyond))


def validate_fixes(fixes: Any, n: int | None, default_sigma: float) -> Float64Array:
    """A drive's fixes as an ``(n, 3)`` array ``x, y, sigma_m`` (NaN rows: no fix).

    ``fixes`` has columns ``x, y[, sigma_m]`` (NaN ``sigma_m``: ``default_sigma``); ``n`` the
    drive's frames (None: any). O(n).

    Raises
    ------
    InputError
        Not ``n`` rows of 2 or 3 columns (a positions file shorter or longer than the drive);
        only one of ``x``, ``y`` NaN; a coordinate infinite or beyond :data:`MAX_COORD_M`; a
        ``sigma_m`` that is not NaN or a finite number > 0.
    """
    arr = np.asarray(fixes, dtype=np.float64)
    if arr.ndim != 2 or not 2 <= arr.shape[1] <= 3 or (n is not None and arr.shape[0] != n):
        rows = arr.shape[0] if arr.ndim == 2 else "?"
        raise InputError(f"GNSS fixes: {rows} rows of shape {arr.shape[1:]} for a drive of "
                         f"{n} frames; expected one row x, y[, sigma_m] per frame")
    out = np.full((len(arr), 3), np.nan)
    out[:, :arr.shape[1]] = arr
    xy = out[:, :2]
    missing = np.isnan(xy)
    bad = np.flatnonzero((missing[:, 0] != missing[:, 1]) | np.isinf(xy).any(axis=1)
                         | (np.abs(np.nan_to_num(xy)) > MAX_COORD_M).any(axis=1))
    if bad.size:
        raise InputError(f"GNSS fixes: frame {int(bad[0])}: x, y {xy[bad[0]].tolist()} out of "
                         f"range (finite, |x|, |y| <= {MAX_COORD_M:g} m; both NaN: no fix)")
    sigma = out[:, 2]
    bad = np.flatnonzero(~np.isnan(sigma) & ~(np.isfinite(sigma) & (sigma > 0)))
    if bad.size:
        raise InputError(f"GNSS fixes: frame {int(bad[0])}: sigma_m {sigma[bad[0]]:g} must be a "
                         "finite number > 0 metres")
    out[np.isnan(sigma), 2] = default_sigma
    out[missing[:, 0], 2] = np.nan
    return out


class PositionIndex:
    """The positions a map stores, by vertex id and in a KD-tree (one map snapshot).

    Parameters
    ----------
    vertices : int
        The map's vertex count (ids ``0..vertices-1``).
    placed : iterable of (first_vertex, positions)
        Each sequence with positions: its first vertex id and its ``(length, 2..5)`` rows
        ``x, y[, heading, time[, sigma_m]]`` (NaN rows: frames without a fix).
    map_sigma : float
        Accuracy of a position without one.

    Notes
    -----
    Built in O(n log n) for the n placed vertices, O(vertices) memory (24 bytes a vertex);
    :meth:`near` is O(log n), :meth:`position` O(1).
    """

    def __init__(self, vertices: int, placed: Any, map_sigma: float) -> None:
        from scipy.spatial import cKDTree

        self.xy = np.full((vertices, 2), np.nan)
        self.sigma = np.full(vertices, np.nan)
        #: direction of travel (radians) of each vertex from its sequence's track (NaN: unknown)
        self.heading = np.full(vertices, np.nan)
        seq = np.full(vertices, -1, dtype=np.int64)
        for i, (first, rows) in enumerate(placed):
            rows = np.asarray(rows, dtype=np.float64)
            stop = min(first + len(rows), vertices)
            xy, sigma = _bridged(rows[:stop - first], map_sigma)
            self.xy[first:stop] = xy
            self.sigma[first:stop] = sigma
            self.heading[first:stop] = track_heading(xy)
            seq[first:stop] = i
        known = np.isfinite(self.xy).all(axis=1)
        self.ids = np.flatnonzero(known)
        self.seq = seq[self.ids]
        self._seq_of = seq
        self.tree = cKDTree(self.xy[self.ids]) if self.ids.size else None

    @property
    def size(self) -> int:
        """Vertices with a position (bridged ones included)."""
        return int(self.ids.size)

    def position(self, vertex_ids: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(xy (m, 2), sigma (m,), heading (m,))`` of vertices (NaN: unknown, or an id beyond
        the snapshot). O(m)."""
        v = np.asarray(vertex_ids, dtype=np.int64)
        inside = (v >= 0) & (v < len(self.sigma))
        xy = np.full((len(v), 2), np.nan)
        sigma = np.full(len(v), np.nan)
        heading = np.full(len(v), np.nan)
        xy[inside] = self.xy[v[inside]]
        sigma[inside] = self.sigma[v[inside]]
        heading[inside] = self.heading[v[inside]]
        return xy, sigma, heading

    def sequence_of(self, vertex_ids: np.ndarray) -> np.ndarray:
        """Index (in the order placed) of each vertex's sequence; -1: none. O(m)."""
        v = np.asarray(vertex_ids, dtype=np.int64)
        out = np.full(len(v), -1, dtype=np.int64)
        inside = (v >= 0) & (v < len(self._seq_of))
        out[inside] = self._seq_of[v[inside]]
        return out

    def near(self, x: float, y: float, k: int = _QUERY_K) -> tuple[np.ndarray, np.ndarray,
                                                                   np.ndarray]:
        """The ``k`` placed vertices nearest ``(x, y)``: ``(ids, metres, sequence index)``,
        nearest first. O(log n + k)."""
        if self.tree is None:
            empty = np.empty(0, dtype=np.int64)
            return empty, np.empty(0), empty
        k = min(k, self.size)
        dist, idx = self.tree.query((x, y), k=k)
        dist, idx = np.atleast_1d(dist), np.atleast_1d(idx)
        return self.ids[idx], dist, self.seq[idx]


class GnssAid:
    """One drive's fixes against a :class:`PositionIndex`: the per-frame cue (module notes).

    Parameters
    ----------
    config : GnssConfig
    index : PositionIndex
    fixes : ndarray (n, 3)
        ``x, y, sigma_m`` per frame, as :func:`validate_fixes` gives them; those inconsistent
        with the drive's track are dropped (:func:`consistent`).

    Notes
    -----
    :meth:`cue` is O(log n + k) per frame: flat as the map grows.
    """

    def __init__(self, config: GnssConfig, index: PositionIndex, fixes: Float64Array) -> None:
        self.config = config
        self.index = index
        self.fixes = np.where(consistent(fixes, config)[:, None], fixes, np.nan)
        #: each frame's direction of travel from the kept fixes (bridged over dropouts)
        self.heading = track_heading(_bridged(self.fixes, config.sigma_m)[0])
        self._cos_gate = math.cos(math.radians(config.heading_gate_deg))

    def fix(self, frame: int) -> tuple[float, float, float] | None:
        """``(x, y, sigma_m)`` of frame ``frame``, or None without a fix."""
        if not 0 <= frame < len(self.fixes):
            return None
        x, y, sigma = self.fixes[frame].tolist()
        return None if math.isnan(x) else (x, y, sigma)

    def cue(self, frame: int, ids: np.ndarray, dists: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
        """Frame ``frame``'s hits with the map vertices near its fix added, each hit's weight
        and the unmapped place's: ``(ids, dists, weights, sink_weight)``; None when the frame
        has no fix or the map no position (nothing changes). O(log n + k)."""
        fix = self.fix(frame)
        if fix is None or self.index.tree is None:
            return None
        x, y, sigma_fix = fix
        cfg = self.config
        ids = np.asarray(ids, dtype=np.int64).ravel()
        dists = np.asarray(dists).ravel()
        valid = ids >= 0
        near_ids, near_m, near_seq = self.index.near(x, y)
        near_sigma = self.index.sigma[near_ids]
        inside = (near_m <= cfg.gate(sigma_fix, near_sigma)) & self._along(
            frame, self.index.heading[near_ids])
        n_image = len(ids)
        if cfg.max_added and inside.any() and valid.any():
            added = near_ids[inside][_round_robin(near_seq[inside])]
            added = added[~np.isin(added, ids[valid])][:cfg.max_added]
            if added.size:
                far = dists[valid].max()
                ids = np.concatenate([ids, added])
                dists = np.concatenate([dists, np.full(added.size, far, dtype=dists.dtype)])
                valid = ids >= 0
        xy, sigma_map, heading = self.index.position(np.where(valid, ids, -1))
        placed = np.isfinite(xy[:, 0])
        weights = np.ones(len(ids))
        weights[n_image:] = math.exp(cfg.added_log_weight)
        d = np.hypot(xy[placed, 0] - x, xy[placed, 1] - y)
        weights[placed] *= cfg.weight(d, sigma_fix, sigma_map[placed])
        weights[placed & ~self._along(frame, heading)] *= math.exp(-cfg.far_log_cap)
        sink_weight = 1.0
        if valid.any() and placed[valid].all() and near_m.size:
            sink_weight = 1.0 / float(cfg.weight(near_m[0], sigma_fix, near_sigma[0]))
        return ids, dists, weights, sink_weight

    def distance(self, frame: int, vertex_id: int | None) -> tuple[float, bool]:
        """Metres from frame ``frame``'s fix to vertex ``vertex_id``'s position (NaN without
        either) and whether the vertex is plausible: inside their gate, and along the frame's
        direction of travel where both are known. O(1)."""
        fix = self.fix(frame)
        if fix is None or vertex_id is None:
            return math.nan, True
        xy, sigma, heading = self.index.position(np.array([vertex_id]))
        if math.isnan(xy[0, 0]):
            return math.nan, True
        d = math.hypot(xy[0, 0] - fix[0], xy[0, 1] - fix[1])
        return d, bool(d <= self.config.gate(fix[2], sigma[0])
                       and self._along(frame, heading)[0])

    def off_track(self, frames: np.ndarray, vertex_ids: np.ndarray) -> np.ndarray:
        """Which decisions (frame, decided vertex; -1: none) break their run's offset: the
        fix minus the place's mapped position lies farther than ``offset_m`` from the median
        of that offset over the decisions on the same sequence within ``consistency_window``
        frames (at least 3 of them). O(n w)."""
        cfg = self.config
        n = len(frames)
        out = np.zeros(n, dtype=bool)
        if not cfg.offset_m or not cfg.consistency_window or not n:
            return out
        xy, _, _ = self.index.position(vertex_ids)
        fixes = self.fixes[np.clip(frames, 0, len(self.fixes) - 1)][:, :2]
        fixes[(frames < 0) | (frames >= len(self.fixes))] = np.nan
        offset = fixes - xy
        known = np.isfinite(offset).all(axis=1) & (vertex_ids >= 0)
        seq = self.index.sequence_of(vertex_ids)
        w = cfg.consistency_window
        for i in np.flatnonzero(known).tolist():
            lo, hi = max(i - w, 0), min(i + w + 1, n)
            near = known[lo:hi] & (seq[lo:hi] == seq[i])
            if near.sum() >= 3:
                median = np.median(offset[lo:hi][near], axis=0)
                out[i] = bool(np.hypot(*(offset[i] - median)) > cfg.offset_m)
        return out

    def _along(self, frame: int, heading: np.ndarray) -> np.ndarray:
        """Whether places of these directions (radians, NaN: unknown) agree with frame
        ``frame``'s direction of travel (True where either is unknown). O(m)."""
        h = float(self.heading[frame]) if 0 <= frame < len(self.heading) else math.nan
        if math.isnan(h):
            return np.ones(len(heading), dtype=bool)
        out: np.ndarray = ~(np.cos(heading - h) < self._cos_gate)  # NaN compares False
        return out


def _round_robin(seq: np.ndarray) -> np.ndarray:
    """Order of candidates (nearest first, of sequences ``seq``): the nearest of each sequence,
    then the second nearest of each, ... (stable by distance within a round). O(k log k)."""
    order = np.argsort(seq, kind="stable")
    by_seq = seq[order]
    starts = np.r_[0, np.flatnonzero(by_seq[1:] != by_seq[:-1]) + 1]
    rank = np.empty(len(seq), dtype=np.int64)
    rank[order] = np.arange(len(seq)) - np.repeat(starts, np.diff(np.r_[starts, len(seq)]))
    out: np.ndarray = np.lexsort((np.arange(len(seq)), rank))
    return out


def _bridged(rows: np.ndarray, map_sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """A sequence's positions ``(xy, sigma)`` with its frames without a fix between two with
    one placed on the line between them (accuracy: the worse of the two plus a quarter of
    their distance); frames before the first or after the last fix stay unknown. O(n)."""
    xy = np.array(rows[:, :2], dtype=np.float64)
    sigma = np.array(rows[:, 4], dtype=np.float64) if rows.shape[1] > 4 \
        else np.full(len(rows), np.nan)
    known = np.isfinite(xy).all(axis=1)
    sigma[known & np.isnan(sigma)] = map_sigma
    sigma[~known] = np.nan
    idx = np.flatnonzero(known)
    if idx.size < 2 or idx.size == len(rows):
        return xy, sigma
    gaps = np.flatnonzero(np.diff(idx) > 1)
    for g in gaps.tolist():
        a, b = int(idx[g]), int(idx[g + 1])
        t = (np.arange(a + 1, b) - a)[:, None] / (b - a)
        xy[a + 1:b] = xy[a] + t * (xy[b] - xy[a])
        sigma[a + 1:b] = max(sigma[a], sigma[b]) + 0.25 * float(np.hypot(*(xy[b] - xy[a])))
    return xy, sigma


def consistent(fixes: Float64Array, config: GnssConfig) -> np.ndarray:
    """Which frames' fixes agree with their drive's track: within ``max(gate_m, 1.5 sigma)``
    of the median (per axis) of the drive's fixes within ``consistency_window`` frames either
    side (at least 3 of them; a frame without one is False). O(n w)."""
    n = len(fixes)
    fixed = ~np.isnan(fixes[:, 0])
    w = config.consistency_window
    if not w or n < 3:
        return fixed
    padded = np.full((n + 2 * w, 2), np.nan)
    padded[w:w + n] = fixes[:, :2]
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * w + 1, axis=0)
    counts = (~np.isnan(windows[:, 0, :])).sum(axis=1)
    enough = fixed & (counts >= 3)
    out = fixed.copy()
    if enough.any():
        median = np.nanmedian(windows[enough], axis=2)
        off = np.hypot(*(fixes[enough, :2] - median).T)
        limit = np.maximum(config.gate_m, 1.5 * fixes[enough, 2])
        out[np.flatnonzero(enough)] = off <= limit
    return out


def track_heading(xy: np.ndarray) -> np.ndarray:
    """Direction of travel (radians) of each frame of a track (``(n, 2)``, NaN rows: no
    position): from the position :data:`HEADING_HALF` frames before to as many after (clipped
    at the ends); NaN where either is unknown or they lie less than
    :data:`HEADING_MIN_SPAN_M` apart. O(n)."""
    n = len(xy)
    idx = np.arange(n)
    a = xy[np.maximum(idx - HEADING_HALF, 0)]
    b = xy[np.minimum(idx + HEADING_HALF, n - 1)]
    d = b - a
    out: np.ndarray = np.arctan2(d[:, 1], d[:, 0])
    with np.errstate(invalid="ignore"):
        out[~(np.hypot(d[:, 0], d[:, 1]) >= HEADING_MIN_SPAN_M)] = np.nan
    return out
