"""A second synthetic world family: descriptor-level drives over latent places (numpy only).

Nothing here is rendered and nothing is shared with the city (:mod:`.city`, :mod:`.layout`,
:mod:`.render`, :mod:`.conditions`, :mod:`.routes`): the world is a street network whose places
are latent vectors, and a frame's descriptor is a fixed nonlinear map of the latent at the
vehicle's place, distorted by the traversal's condition, plus noise. It exists so that what is
tuned on the rendered city can be checked on a world built another way (issue 28).

The world, and why each part is there:

- **streets**: a jittered grid of intersections (``grid``, ``block_m`` apart; a few km of street
  in all) with a few streets removed; every street has a latent sequence per direction (the
  other way the car sees other things), sampled every metre;
- **latent places**: a *style* part (``style_dim``: one of ``n_styles`` shared looks plus a slow
  drift, so streets of one style resemble each other) and a *place* part (``latent_dim -
  style_dim``): an AR(1) random walk along the street with correlation length ``corr_m``, so
  neighbouring places look alike and appearance changes smoothly;
- **lookalikes**: ``lookalike_streets`` of the streets copy another street's style and a share
  ``rho`` (U(``lookalike_rho``)) of its place part, the rest their own: similar, not identical
  (realistic perceptual aliasing);
- **identical twins**: ``twin_streets`` streets whose latents are exactly another street's (both
  directions, stretched to their length): no image-only method can tell them apart; their
  frames are listed in ``dataset.json`` (``twins``) so evaluations report them separately;
- **descriptors**: ``x = B tanh(A z + b)`` (fixed random ``A``, ``B``; ``dim`` outputs), then the
  condition, then noise, then L2 normalisation;
- **conditions** (:data:`CONDITIONS`): each a fixed (per world and name) structured distortion of
  a strength from mild (``day``) to strong (``night``, ``snow``): a linear mixing ``I + s G``,
  per-channel gains ``exp(s g)``, an offset, gains on the style and place parts of the latent,
  and white plus time-correlated noise (traffic, rain passing the camera); each traversal
  jitters its condition a little;
- **seasons** (optional, ``seasons``; :data:`SEASONS`): a season is a fixed direction per world
  and season name in descriptor space, shared by every drive of that season; a drive of season
  ``s`` has ``season_strength`` (jittered per drive) times that direction added to every
  descriptor before the noise and the normalisation, so the place signal is intact under it
  but every descriptor of the season leans the same way (what snow does to a global
  descriptor: a query in winter is pulled towards every winter drive of the map). Off (``()``)
  by default, and then nothing is drawn for it: the worlds are bit-identical to those without;
- **drives**: a route over the streets (no U-turns but at dead ends), driven at a per-traversal
  speed with a smooth speed profile, stops and a lateral lane offset, with a per-frame pose jitter
  along the street; each traversal after the first is the candidate route (of
  :data:`ROUTE_CANDIDATES`) that best meets ``novel_fraction`` (frames with no true match among
  earlier traversals) and ``reverse_fraction`` (of them, on streets driven only the other way).

Ground truth is by position (``radius_m``, ``heading_deg``), as for the city. Determinism:
everything derives from ``seed``; traversal ``i`` depends only on the seed and traversals ``< i``.
Cost: O(total frames x (dim x hidden)) for the descriptors plus O(candidates x frames x log n)
for the route search: ~1 s for 10 traversals x 300 frames.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from sprint_map.errors import InputError
from sprint_map.frontend.dataset import frame_ranges
from sprint_map.frontend.groundtruth import GroundTruth, GroundTruthSpec
from sprint_map.util import dataclass_dict
from sprint_map.util.arrays import Float64Array
from sprint_map.util.union_find import UnionFind

__all__ = ["CONDITIONS", "LATENT_PRESETS", "LatentCondition", "LatentConfig", "LatentTraversal",
           "LatentWorld", "ROUTE_CANDIDATES", "SEASONS", "generate_latent", "make_latent"]

#: Candidate routes drawn per traversal when ``novel_fraction`` or ``reverse_fraction`` is set.
ROUTE_CANDIDATES = 40
#: Share of frames a novelty-seeking traversal should still have on known ground.
MIN_MATCHED = 0.2
_HIDDEN = 128  # width of the nonlinear map's hidden layer
_OFFSET = 0.15  # a condition's shift of every descriptor, per unit of strength
#: The season names a world may use (``LatentConfig.seasons``); each has its own direction.
SEASONS = ("summer", "autumn", "winter", "spring")


@dataclass(frozen=True)
class LatentCondition:
    """A condition as a structured distortion of the descriptors.

    ``strength`` scales the linear mixing, channel gains and offset; ``noise`` and
    ``temporal_noise`` scale the white and time-correlated per-frame noise (times the world's
    ``noise``; their squares sum to ~1 for every condition, so no condition's descriptors are
    noisier overall, only noisier over time); ``style_gain`` and ``place_gain`` multiply the two latent parts (night dims the
    details that tell places apart).
    """

    strength: float
    noise: float
    temporal_noise: float
    style_gain: float = 1.0
    place_gain: float = 1.0


#: The conditions, mild to strong.
CONDITIONS: dict[str, LatentCondition] = {
    "day": LatentCondition(0.10, 0.8, 0.6),
    "overcast": LatentCondition(0.20, 0.75, 0.66),
    "dusk": LatentCondition(0.35, 0.7, 0.71, place_gain=0.9),
    "rain": LatentCondition(0.45, 0.5, 0.87, place_gain=0.9),
    "night": LatentCondition(0.70, 0.8, 0.6, style_gain=1.1, place_gain=0.75),
    "snow": LatentCondition(0.60, 0.7, 0.71, style_gain=0.7, place_gain=0.9),
}


@dataclass(frozen=True)
class LatentConfig:
    """Parameters of the latent world and of how it is driven (see the module docstring).

    Distances in metres. ``noise`` is the calibration knob of difficulty: with the defaults,
    exact k-NN@1 is ~30-45 % and k-NN@10 ~70-80 % of the frames with a true match.
    """

    grid: tuple[int, int] = (5, 5)
    block_m: float = 150.0
    jitter_m: float = 20.0
    drop_streets: float = 0.1
    dim: int = 256
    latent_dim: int = 48
    style_dim: int = 16
    n_styles: int = 4
    corr_m: float = 15.0
    lookalike_streets: float = 0.3
    lookalike_rho: tuple[float, float] = (0.6, 0.85)
    twin_streets: int = 1
    noise: float = 1.8
    temporal_m: float = 20.0
    pose_m: float = 1.5
    speed_m: float = 3.0
    stop_prob: float = 0.15
    revisit: float = 3.0
    conditions: tuple[str, ...] = ("day", "overcast", "dusk", "rain", "night", "snow")
    radius_m: float = 8.0
    heading_deg: float = 45.0
    novel_fraction: float = 0.0
    reverse_fraction: float = 0.0
    #: Season of drive ``i``: ``seasons[i % len(seasons)]`` (names from :data:`SEASONS`); ``()``:
    #: no season (and nothing drawn for it).
    seasons: tuple[str, ...] = ()
    #: Length of a season's shift of every descriptor, in units of the place signal's length.
    season_strength: float = 0.6

    def __post_init__(self) -> None:
        if len(self.grid) != 2 or min(self.grid) < 2:
            raise ValueError("grid must be two integers >= 2")
        if not self.conditions or any(c not in CONDITIONS for c in self.conditions):
            raise ValueError(f"conditions must be names from {', '.join(CONDITIONS)}")
        if any(c not in SEASONS for c in self.seasons):
            raise ValueError(f"seasons must be names from {', '.join(SEASONS)}")
        if not 0 <= self.season_strength <= 10:
            raise ValueError("season_strength must be in [0, 10]")
        if not 0 < self.style_dim < self.latent_dim or self.dim < 2 or self.n_styles < 1:
            raise ValueError("need 0 < style_dim < latent_dim, dim >= 2, n_styles >= 1")
        if self.block_m <= 4 * self.jitter_m or self.jitter_m < 0 or self.corr_m <= 0:
            raise ValueError("need 0 <= 4 * jitter_m < block_m and corr_m > 0")
        if not 0 <= self.drop_streets <= 0.3 or not 0 <= self.lookalike_streets <= 0.5:
            raise ValueError("drop_streets must be in [0, 0.3], lookalike_streets in [0, 0.5]")
        lo, hi = self.lookalike_rho
        if not 0 <= lo <= hi < 1 or self.twin_streets < 0:
            raise ValueError("lookalike_rho must satisfy 0 <= lo <= hi < 1; twin_streets >= 0")
        if self.speed_m <= 0 or self.noise < 0 or self.pose_m < 0 or self.temporal_m <= 0:
            raise ValueError("speed_m and temporal_m must be > 0, noise and pose_m >= 0")
        if not 0 <= self.stop_prob <= 1 or self.revisit <= 0:
            raise ValueError("stop_prob must be in [0, 1], revisit > 0")
        if not 0 <= self.reverse_fraction <= self.novel_fraction <= 1 - MIN_MATCHED:
            raise ValueError(
                f"need 0 <= reverse_fraction <= novel_fraction <= {1 - MIN_MATCHED}")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> LatentConfig:
        """Build from a dict (raises ConfigError on unknown keys or bad values)."""
        return dataclass_dict.from_dict(cls, data)

    def to_dict(self) -> dict[str, Any]:
        """Return a JSON-ready dict (without the season keys when there is no season, so the
        ``dataset.json`` of a world without seasons is what it was before seasons existed)."""
        out = dataclass_dict.to_dict(self)
        if not self.seasons:
            del out["seasons"], out["season_strength"]
        return out

    def ground_truth_spec(self) -> GroundTruthSpec:
        """The position alignment written to ``dataset.json``."""
        return GroundTruthSpec("position", radius_m=self.radius_m, heading_deg=self.heading_deg)

    def season_of(self, index: int) -> str | None:
        """The season of drive ``index`` (None without seasons)."""
        return self.seasons[index % len(self.seasons)] if self.seasons else None


#: The demo's latent world (``sprint-map demo --dataset latent``): each traversal after the first
#: spends at least half of its frames where no earlier one was (10 % on streets driven the other
#: way). ``latent-lifelong``: the same world driven mostly over known streets (for 24 traversals).
LATENT_PRESETS: dict[str, LatentConfig] = {
    "latent": LatentConfig(novel_fraction=0.5, reverse_fraction=0.1),
    "latent-lifelong": LatentConfig(grid=(4, 4), novel_fraction=0.2, reverse_fraction=0.05),
}


@dataclass
class LatentTraversal:
    """One drive of a latent world.

    Attributes
    ----------
    name, condition : str
    descriptors : (N, dim) float32, L2-normalised
    positions : (N, 4) float64
        ``frame, x, y, heading_deg``, as :func:`~sprint_map.frontend.positions.read_positions`
        returns them.
    street : (N,) int
        Directed street of each frame (``2 * street + direction``).
    twin : (N,) bool
        Frames on an identical-twin street (either of a pair, either direction).
    season : str or None
        The drive's season (``LatentConfig.seasons``), None without seasons.
    """

    name: str
    condition: str
    descriptors: np.ndarray
    positions: Float64Array
    street: np.ndarray
    twin: np.ndarray
    season: str | None = None


@dataclass
class LatentWorld:
    """A generated latent world: its traversals and ground truth."""

    config: LatentConfig
    seed: int
    traversals: list[LatentTraversal] = field(default_factory=list)
    #: Street -> (the street it looks like, share ``rho`` of its place latent taken).
    lookalikes: dict[int, tuple[int, float]] = field(default_factory=dict)
    #: Street -> the street it is an identical twin of.
    twins: dict[int, int] = field(default_factory=dict)
    #: Per directed street (``2 * street + direction``): its latents, one row per metre.
    latents: list[np.ndarray] = field(default_factory=list)

    @property
    def names(self) -> list[str]:
        """Traversal names, in order."""
        return [t.name for t in self.traversals]

    def ground_truth(self) -> GroundTruth:
        """Position ground truth over the traversals (radius and heading from the config)."""
        return GroundTruth(self.config.ground_truth_spec(),
                           positions={t.name: t.positions for t in self.traversals})


class _Network:
    """Intersections, streets and the latent sequence of every directed street."""

    def __init__(self, config: LatentConfig, rng: np.random.Generator) -> None:
        nx, ny = config.grid
        grid = np.array([(i, j) for j in range(ny) for i in range(nx)], dtype=np.float64)
        self.nodes = grid * config.block_m + rng.uniform(-config.jitter_m, config.jitter_m,
                                                         grid.shape)
        edges = []
        for j in range(ny):
            for i in range(nx):
                n = j * nx + i
                if i + 1 < nx:
                    edges.append((n, n + 1))
                if j + 1 < ny:
                    edges.append((n, n + nx))
        self.edges = _drop_edges(edges, len(self.nodes), config.drop_streets, rng)
        self.adjacent: dict[int, list[int]] = {n: [] for n in range(len(self.nodes))}
        for e, (a, b) in enumerate(self.edges):
            self.adjacent[a].append(e)
            self.adjacent[b].append(e)
        self.length = np.array([np.hypot(*(self.nodes[b] - self.nodes[a]))
                                for a, b in self.edges])
        self.latents, self.lookalikes, self.twins = _latents(config, self, rng)

    def ends(self, directed: int) -> tuple[int, int]:
        """Start and end node of a directed street (``2 * street + direction``)."""
        a, b = self.edges[directed // 2]
        return (a, b) if directed % 2 == 0 else (b, a)


def _drop_edges(edges: list[tuple[int, int]], n_nodes: int, share: float,
                rng: np.random.Generator) -> list[tuple[int, int]]:
    """Remove up to ``share`` of the streets, keeping every intersection reachable."""
    kept = list(edges)
    for k in rng.permutation(len(edges))[: int(share * len(edges))]:
        trial = [e for e in kept if e != edges[int(k)]]
        if _connected(trial, n_nodes):
            kept = trial
    return kept


def _connected(edges: list[tuple[int, int]], n_nodes: int) -> bool:
    sets = UnionFind(n_nodes)
    for a, b in edges:
        sets.union(a, b)
    return len(sets.groups()) == 1


def _ar1(rng: np.random.Generator, n: int, dim: int, corr: float) -> np.ndarray:
    """``n`` steps (1 m apart) of a unit-variance AR(1) walk with correlation length ``corr``."""
    a = float(np.exp(-1.0 / corr))
    out = np.empty((n, dim))
    out[0] = rng.standard_normal(dim)
    eps = rng.standard_normal((n, dim)) * np.sqrt(1 - a * a)
    for k in range(1, n):
        out[k] = a * out[k - 1] + eps[k]
    return out


def _stretch(seq: np.ndarray, n: int) -> np.ndarray:
    """Resample a per-metre sequence to ``n`` samples (linear interpolation)."""
    src = np.linspace(0, len(seq) - 1, n)
    lo = np.floor(src).astype(int)
    hi = np.minimum(lo + 1, len(seq) - 1)
    t = (src - lo)[:, None]
    return np.asarray(seq[lo] * (1 - t) + seq[hi] * t)


def _latents(config: LatentConfig, net: _Network, rng: np.random.Generator
             ) -> tuple[list[np.ndarray], dict[int, tuple[int, float]], dict[int, int]]:
    """Per directed street, its latent sequence (one row per metre); lookalike streets (street ->
    (source street, rho)) and identical twins (street -> source street)."""
    styles = rng.standard_normal((config.n_styles, config.style_dim))
    n_place = config.latent_dim - config.style_dim
    out: list[np.ndarray] = []
    for length in net.length:
        n = int(np.ceil(length)) + 1
        for _direction in range(2):
            style = styles[int(rng.integers(config.n_styles))]
            drift = 0.5 * _ar1(rng, n, config.style_dim, 4 * config.corr_m)
            place = _ar1(rng, n, n_place, config.corr_m)
            out.append(np.hstack([style + drift, place]))
    n_streets = len(net.edges)
    order = [int(k) for k in rng.permutation(n_streets)]
    n_twins = min(config.twin_streets, n_streets // 2)
    n_look = min(int(config.lookalike_streets * n_streets), n_streets - 2 * n_twins)
    twins: dict[int, int] = {}
    for k in range(n_twins):
        copy, source = order[2 * k], order[2 * k + 1]
        twins[copy] = source
        for d in range(2):
            out[2 * copy + d] = _stretch(out[2 * source + d], len(out[2 * copy + d]))
    lookalikes: dict[int, tuple[int, float]] = {}
    rest = order[2 * n_twins:]
    originals = rest[n_look:]
    for copy in rest[:n_look]:
        source = originals[int(rng.integers(len(originals)))]
        rho = float(rng.uniform(*config.lookalike_rho))
        lookalikes[copy] = (source, rho)
        for d in range(2):
            mine, theirs = out[2 * copy + d], _stretch(out[2 * source + d], len(out[2 * copy + d]))
            style = theirs[:, : config.style_dim]
            place = rho * theirs[:, config.style_dim:] + np.sqrt(1 - rho * rho) * mine[
                :, config.style_dim:]
            out[2 * copy + d] = np.hstack([style, place])
    return out, lookalikes, twins


class _Appearance:
    """The fixed descriptor map and the conditions' fixed distortions of one world."""

    def __init__(self, config: LatentConfig, seed: int) -> None:
        self.config = config
        rng = np.random.default_rng([seed, 10])
        self.a = rng.standard_normal((config.latent_dim, _HIDDEN)) * 1.2 / np.sqrt(
            config.latent_dim)
        self.b = rng.standard_normal(_HIDDEN) * 0.3
        self.w = rng.standard_normal((_HIDDEN, config.dim)) / np.sqrt(_HIDDEN)
        sample = np.tanh(rng.standard_normal((2048, config.latent_dim)) @ self.a + self.b) @ self.w
        self.center = sample.mean(axis=0)
        #: Typical size of the place-dependent part: the unit of mean, offsets and noise.
        self.unit = float(np.sqrt(np.mean((sample - self.center) ** 2)))
        self.mean = np.abs(rng.standard_normal(config.dim)) * 0.5  # descriptors are not centred
        self.distortions: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        for k, name in enumerate(CONDITIONS):
            crng = np.random.default_rng([seed, 11, k])
            mix = crng.standard_normal((config.dim, config.dim)) / np.sqrt(config.dim)
            gain = crng.standard_normal(config.dim)
            offset = crng.standard_normal(config.dim)
            self.distortions[name] = (mix, gain, offset)
        #: Per season, a unit direction of the descriptor space (drawn only when used).
        self.seasons: dict[str, np.ndarray] = {}
        for name in config.seasons:
            if name not in self.seasons:
                srng = np.random.default_rng([seed, 12, SEASONS.index(name)])
                direction = srng.standard_normal(config.dim)
                self.seasons[name] = direction / np.linalg.norm(direction)

    def clean(self, latent: np.ndarray, condition: LatentCondition) -> np.ndarray:
        """The place-dependent part of the descriptors of latent rows (centred; before the
        condition's linear part)."""
        s = self.config.style_dim
        z = np.hstack([latent[:, :s] * condition.style_gain, latent[:, s:] * condition.place_gain])
        return np.asarray(np.tanh(z @ self.a + self.b) @ self.w - self.center)

    def describe(self, latent: np.ndarray, name: str, condition: LatentCondition,
                 rng: np.random.Generator, frames_per_m: np.ndarray,
                 season: tuple[str, float] | None = None) -> np.ndarray:
        """Descriptors of one traversal's latent rows under ``condition`` (jittered by ``rng``),
        with white and time-correlated noise; L2-normalised float32. ``season``: its name and
        this drive's strength; that times the season's direction (scaled to the place signal's
        length, ``unit * sqrt(dim)``) is added to every row before the noise."""
        mix, gain, offset = self.distortions[name]
        s = condition.strength
        jitter = 1 + 0.15 * rng.standard_normal(3)
        x = self.clean(latent, condition)
        x = x + (s * jitter[0]) * (x @ mix.T)
        x = x * np.exp(0.3 * s * jitter[1] * gain)
        x = x + self.unit * (self.mean + _OFFSET * s * jitter[2] * offset)
        if season is not None:
            x = x + (season[1] * self.unit * np.sqrt(self.config.dim)) * self.seasons[season[0]]
        n = len(x)
        scale = self.config.noise * self.unit
        white = rng.standard_normal(x.shape) * condition.noise
        # Time-correlated noise: an AR(1) over frames whose correlation follows distance driven
        # (a passing truck, rain on the windscreen), unit variance.
        a = np.exp(-1.0 / np.maximum(self.config.temporal_m * frames_per_m, 1e-6))
        slow = np.empty_like(x)
        slow[0] = rng.standard_normal(x.shape[1])
        eps = rng.standard_normal(x.shape)
        for k in range(1, n):
            slow[k] = a[k] * slow[k - 1] + np.sqrt(1 - a[k] ** 2) * eps[k]
        x = x + scale * (white + condition.temporal_noise * slow)
        x /= np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)
        return np.asarray(x, dtype=np.float32)


@dataclass(frozen=True)
class _Route:
    """A driven route: frame positions and where on which directed street each frame is."""

    xy: np.ndarray
    heading_deg: np.ndarray
    street: np.ndarray  # directed street per frame
    arc: np.ndarray  # metres from the directed street's start
    step: np.ndarray  # metres driven to reach each frame (frames per metre = 1 / step)


def _plan(net: _Network, config: LatentConfig, length: float, driven: set[int],
          rng: np.random.Generator, new_weight: float, reverse_weight: float) -> list[int]:
    """A route of directed streets at least ``length`` m long, mostly starting where an
    earlier drive went: no U-turn except at a dead end; driven streets weighted ``revisit``, streets driven only the other way
    ``reverse_weight``, new ones ``new_weight``."""
    known = sorted({net.ends(d)[0] for d in driven})
    # Most drives set off from somewhere the map knows (home, depot), some from anywhere.
    node = (known[int(rng.integers(len(known)))] if known and rng.random() < 0.8
            else int(rng.integers(len(net.nodes))))
    route: list[int] = []
    total = 0.0
    while total < length:
        options = []
        for e in net.adjacent[node]:
            a, _ = net.edges[e]
            directed = 2 * e + (0 if a == node else 1)
            if route and directed // 2 == route[-1] // 2 and len(net.adjacent[node]) > 1:
                continue  # no U-turn
            options.append(directed)
        weights = np.array([config.revisit if d in driven else
                            reverse_weight if (d ^ 1) in driven else new_weight
                            for d in options])
        choice = options[int(rng.choice(len(options), p=weights / weights.sum()))]
        route.append(choice)
        total += float(net.length[choice // 2])
        node = net.ends(choice)[1]
    return route


def _drive(net: _Network, config: LatentConfig, route: list[int], frames: int, speed: float,
           lane: float, rng: np.random.Generator) -> _Route:
    """Frames along ``route``: a smooth speed profile around ``speed`` m/frame, stops of 3-12
    frames before some intersections, ``lane`` metres right of the street's centre line."""
    starts = np.concatenate([[0.0], np.cumsum([net.length[d // 2] for d in route])])
    stop_at = {k for k in range(1, len(route)) if rng.random() < config.stop_prob}
    wobble = _ar1(rng, frames, 1, 15.0)[:, 0]
    steps = np.clip(speed * (1 + 0.25 * wobble), 0.3 * speed, 1.8 * speed)
    arc_total = np.empty(frames)
    pos, k, stopped, seg = 0.0, 0, 0, 0
    while k < frames:
        while seg + 1 < len(starts) - 1 and pos >= starts[seg + 1]:
            seg += 1
        nxt = seg + 1
        if stopped == 0 and nxt in stop_at and starts[nxt] - 6 <= pos < starts[nxt]:
            stop_at.discard(nxt)
            stopped = int(rng.integers(3, 13))
        if stopped:
            stopped -= 1
            step = 0.05 * speed
        else:
            step = float(steps[k])
        pos = min(pos + step, starts[-1] - 1e-6) if k else pos
        arc_total[k] = pos
        k += 1
    seg_of = np.searchsorted(starts, arc_total, side="right") - 1
    seg_of = np.clip(seg_of, 0, len(route) - 1)
    directed = np.array(route)[seg_of]
    arc = arc_total - starts[seg_of]
    ends = np.array([net.ends(int(d)) for d in directed])
    u = (net.nodes[ends[:, 1]] - net.nodes[ends[:, 0]]) / net.length[directed // 2][:, None]
    right = np.column_stack([u[:, 1], -u[:, 0]])
    xy = net.nodes[ends[:, 0]] + arc[:, None] * u + lane * right
    heading = np.degrees(np.arctan2(u[:, 1], u[:, 0])) % 360.0
    step_out = np.diff(arc_total, prepend=arc_total[0] - speed)
    return _Route(xy, heading, directed, arc, np.maximum(step_out, 1e-3))


def _overlap(route: _Route, tree: cKDTree, earlier_heading: np.ndarray,
             radius: float, heading: float) -> tuple[np.ndarray, np.ndarray]:
    """Per frame: a true match among the earlier frames (``tree`` of their positions); seen
    only the other way. O(frames x log(earlier frames))."""
    near = tree.query_ball_point(route.xy, radius)
    counts = np.fromiter((len(n) for n in near), dtype=np.int64, count=len(near))
    if counts.sum() == 0:
        return np.zeros(len(near), dtype=bool), np.zeros(len(near), dtype=bool)
    frame = np.repeat(np.arange(len(near)), counts)
    other = np.concatenate([n for n in near if n]).astype(np.int64)
    diff = np.abs((earlier_heading[other] - route.heading_deg[frame] + 180) % 360 - 180)
    matched = np.bincount(frame[diff <= heading], minlength=len(near)) > 0
    opposite = (np.bincount(frame[diff >= 180 - heading], minlength=len(near)) > 0) & ~matched
    return matched, opposite


def make_latent(n_traversals: int = 10, frames_per_traversal: int = 300, seed: int = 0,
                config: LatentConfig | None = None) -> LatentWorld:
    """Generate a latent world in memory.

    Cost: O(n_traversals x (ROUTE_CANDIDATES x frames x log(earlier frames) + frames x dim x
    128)); memory ``n_traversals x frames x dim x 4`` bytes of descriptors.
    """
    config = config or LatentConfig()
    if n_traversals < 1 or frames_per_traversal < 1:
        raise ValueError("n_traversals and frames_per_traversal must be >= 1")
    net = _Network(config, np.random.default_rng([seed, 0]))
    look = _Appearance(config, seed)
    world = LatentWorld(config, seed, lookalikes=net.lookalikes, twins=net.twins,
                        latents=net.latents)
    twin_streets = set(net.twins) | set(net.twins.values())
    driven: set[int] = set()
    earlier_xy: list[np.ndarray] = []
    earlier_heading: list[np.ndarray] = []
    for i in range(n_traversals):
        rng = np.random.default_rng([seed, 1, i])
        name = config.conditions[i % len(config.conditions)]
        speed = config.speed_m * float(rng.uniform(0.7, 1.3))
        lane = float(rng.uniform(1.0, 3.0))
        length = frames_per_traversal * speed * 1.8 + config.block_m
        if i == 0 or config.novel_fraction == 0:
            route = _drive(net, config, _plan(net, config, length, driven, rng, 1.0, 1.0),
                           frames_per_traversal, speed, lane, rng)
        else:
            route = _novel_route(net, config, i, seed, length, driven, frames_per_traversal,
                                 speed, lane, np.concatenate(earlier_xy),
                                 np.concatenate(earlier_heading))
        driven.update(int(d) for d in route.street)
        earlier_xy.append(route.xy)
        earlier_heading.append(route.heading_deg)
        pose = rng.normal(0, config.pose_m, len(route.arc)) if config.pose_m else 0.0
        latent = np.empty((len(route.arc), config.latent_dim))
        for k, (d, s) in enumerate(zip(route.street, route.arc + pose, strict=True)):
            seq = net.latents[int(d)]
            s = float(np.clip(s, 0, len(seq) - 1))
            lo = int(s)
            hi = min(lo + 1, len(seq) - 1)
            latent[k] = seq[lo] * (1 - (s - lo)) + seq[hi] * (s - lo)
        season = config.season_of(i)
        # The season's strength is jittered per drive from its own stream, so a world without
        # seasons draws exactly what it drew before seasons existed.
        shift = None if season is None else (season, config.season_strength * float(
            1 + 0.1 * np.random.default_rng([seed, 13, i]).standard_normal()))
        descriptors = look.describe(latent, name, CONDITIONS[name],
                                    np.random.default_rng([seed, 2, i]), 1.0 / route.step, shift)
        frames = np.arange(len(route.xy), dtype=np.float64)
        world.traversals.append(LatentTraversal(
            name=f"t{i:02d}-{name}" + (f"-{season}" if season else ""), condition=name,
            descriptors=descriptors,
            positions=np.column_stack([frames, route.xy, route.heading_deg]),
            street=route.street.copy(),
            twin=np.isin(route.street // 2, list(twin_streets)), season=season))
    return world


def _novel_route(net: _Network, config: LatentConfig, i: int, seed: int, length: float,
                 driven: set[int], frames: int, speed: float, lane: float,
                 earlier_xy: np.ndarray, earlier_heading: np.ndarray) -> _Route:
    """The first candidate route meeting the novelty targets, else the one missing them least."""
    best: tuple[float, _Route] | None = None
    tree = cKDTree(earlier_xy)
    for c in range(ROUTE_CANDIDATES):
        rng = np.random.default_rng([seed, 3, i, c])
        plan = _plan(net, config, length, driven, rng, float(rng.uniform(1.0, 12.0)),
                     float(rng.uniform(0.5, 8.0)))
        route = _drive(net, config, plan, frames, speed, lane, rng)
        matched, opposite = _overlap(route, tree, earlier_heading, config.radius_m,
                                     config.heading_deg)
        shortfall = (4 * max(0.0, config.novel_fraction - (1 - matched.mean()))
                     + 2 * max(0.0, config.reverse_fraction - opposite.mean())
                     + 3 * max(0.0, MIN_MATCHED - matched.mean()))
        if best is None or shortfall < best[0]:
            best = (shortfall, route)
        if shortfall == 0:
            break
    assert best is not None
    return best[1]


def generate_latent(out_dir: str | Path, n_traversals: int = 10, frames_per_traversal: int = 300,
                    seed: int = 0, config: LatentConfig | None = None) -> Path:
    """Write a latent world as a data set that :class:`~sprint_map.frontend.dataset.Dataset`
    reads (``sprint-map eval`` evaluates it with its precomputed descriptors).

    Layout::

        out_dir/dataset.json            {"alignment": "position", ..., "twins": {...}}
        out_dir/t00-day/descriptors.npy (N, dim) float32
        out_dir/t00-day/positions.csv   frame,x,y,heading_deg
        out_dir/t01-overcast/ ...

    ``twins`` maps each traversal to its frames on identical-twin streets, as ``[start, stop)``
    ranges. Written to a hidden sibling and renamed into place, so an interrupted run leaves
    nothing under ``out_dir``.

    Raises
    ------
    InputError
        If ``out_dir`` exists and is not an empty directory.
    """
    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(f"{out}: exists and is not an empty directory")
    config = config or LatentConfig()
    world = make_latent(n_traversals, frames_per_traversal, seed, config)
    staging = out.parent / f".{out.name}.partial-{os.getpid()}"
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    try:
        for t in world.traversals:
            folder = staging / t.name
            folder.mkdir()
            np.save(folder / "descriptors.npy", t.descriptors)
            with (folder / "positions.csv").open("w", encoding="utf-8") as handle:
                handle.write("frame,x,y,heading_deg\n")
                for frame, x, y, heading in t.positions:
                    handle.write(f"{int(frame)},{x:.3f},{y:.3f},{heading:.2f}\n")
        description = {
            **config.ground_truth_spec().to_dict(),
            "description": (f"Synthetic latent world (sprint_map.synth.latent), {n_traversals} "
                            f"traversals x {frames_per_traversal} frames, seed {seed}"),
            "twins": {t.name: frame_ranges(t.twin) for t in world.traversals},
            "generator": {
                "module": "sprint_map.synth.latent",
                "seed": seed,
                "frames_per_traversal": frames_per_traversal,
                "config": config.to_dict(),
                "lookalike_streets": {str(k): list(v) for k, v in world.lookalikes.items()},
                "twin_streets": {str(k): v for k, v in world.twins.items()},
            },
        }
        (staging / "dataset.json").write_text(json.dumps(description, indent=2) + "\n")
        if out.exists():
            out.rmdir()
        os.replace(staging, out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return out
