"""Synthetic multi-traversal city data sets: the public entry points of :mod:`sprint_map.synth`.

:func:`render_city` returns traversals in memory (for tests); :func:`generate_city` writes the
on-disk data-set layout that :class:`~sprint_map.frontend.dataset.Dataset` reads: one folder per
traversal with numbered images and ``positions.csv`` (``frame,x,y,heading_deg``), and a
``dataset.json`` declaring position alignment.

What varies between traversals, and why:

- the route (:mod:`.routes`): traversals overlap but also drive novel streets, or known streets
  the other way, where a query has no correct match; with ``novel_fraction`` each traversal
  after the first is chosen among candidate routes to spend at least that share of its frames
  where no earlier traversal was (``reverse_fraction`` of them on streets driven the other way);
- the city itself: ``alias_streets`` makes some streets copies of others (false matches);
- the condition (:mod:`.conditions`): light, weather, traffic;
- the season (:mod:`.seasons`, optional, ``seasons``): a change of the whole scene (snow on the
  ground and snowbanks, or foliage) that is the same in every frame of every drive of a season,
  so it is a shared component of their descriptors; off by default, and then nothing is drawn
  for it (a world without seasons is bit-identical to one rendered before seasons existed);
- the driving: speed profile, stops, lane offset, camera height, pitch and a slow yaw wobble, so
  the same place is never seen from exactly the same pose.

Presets: :data:`PRESETS` names the demo's worlds (``city``, ``city-novel``).

Determinism: everything derives from ``seed``. Traversal ``i`` depends only on ``seed`` and on the
routes of traversals ``< i``, so asking for more traversals leaves the first ones unchanged, and
the output does not depend on ``workers``.

Throughput: building the city (layout and ~350 facade textures) takes ~0.8 s; a 160x120 frame
takes ~3-4 ms to render and condition, plus ~0.3 ms to encode as PNG. Traversals are rendered
in parallel threads (OpenCV and large numpy operations release the GIL).
"""

from __future__ import annotations

import json
import os
import shutil
from collections import deque
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sprint_map.errors import ConfigError, InputError
from sprint_map.frontend.dataset import frame_ranges
from sprint_map.frontend.groundtruth import GroundTruth, GroundTruthSpec
from sprint_map.frontend.parallel import default_workers
from sprint_map.synth.atlas import Atlas, build_atlas
from sprint_map.synth.conditions import CONDITIONS, Appearance, Condition
from sprint_map.synth.layout import CityLayout, Node, build_layout
from sprint_map.synth.render import Camera, Renderer
from sprint_map.synth.routes import Drive, Edge, Trajectory, drive, overlap, plan_route
from sprint_map.synth.seasons import SEASONS, SeasonLook
from sprint_map.util import dataclass_dict
from sprint_map.util.arrays import Float64Array, Image

__all__ = ["CityConfig", "IMAGE_FORMATS", "MIN_MATCHED", "PRESETS", "ROUTE_CANDIDATES",
           "SyntheticCity", "SyntheticTraversal", "TraversalPlan", "generate_city", "iter_city",
           "render_city"]

IMAGE_FORMATS = ("png", "jpg")
#: Candidate routes drawn per traversal when ``novel_fraction`` or ``reverse_fraction`` is set.
ROUTE_CANDIDATES = 40
#: Share of frames a novelty-seeking traversal should still have on known ground.
MIN_MATCHED = 0.2


@dataclass(frozen=True)
class CityConfig:
    """Parameters of the synthetic city and of how it is driven.

    Each field is described by the comment above it.
    """

    #: Intersections along x and y.
    grid: tuple[int, int] = (4, 4)
    #: Distance between intersections (metres).
    block_m: float = 60.0
    #: Street width between facades.
    street_m: float = 14.0
    #: Facade styles shared by all street sides: fewer styles, more perceptual aliasing.
    n_styles: int = 4
    #: Individual details (posters, signs, trees, ...) per 10 m of facade: more details, more
    #: distinctive places.
    detail: float = 1.0
    #: Image size in pixels.
    width: int = 160
    height: int = 120
    #: Horizontal field of view.
    fov_deg: float = 90.0
    #: Mean distance driven per frame (each drive scales it by U(0.7, 1.3)).
    speed_m: float = 2.0
    #: Chance of stopping for 3-12 frames before each intersection.
    stop_prob: float = 0.25
    #: Preference for streets already driven (weight against 1 for new ones).
    revisit: float = 3.0
    #: Condition of drive ``i`` is ``conditions[i % len(conditions)]`` (see
    #: :data:`~sprint_map.synth.conditions.CONDITIONS`), jittered per drive.
    conditions: tuple[str, ...] = ("day", "overcast", "dusk", "rain", "fog", "snow")
    #: Per-frame camera shake: yaw sd in degrees, pitch sd in pixels.
    shake: float = 1.5
    #: Ground truth written to ``dataset.json``: same place within
    #: ``radius_m`` metres and ``heading_deg`` degrees of heading.
    radius_m: float = 8.0
    heading_deg: float = 45.0
    #: Share of the streets (at most 0.5) that are copies of another street: the same facade
    #: styles and rhythm of buildings, but other buildings, signs and gaps (lookalikes, see
    #: :func:`.layout.build_layout`).
    alias_streets: float = 0.0
    #: How many of those copies are pixel-identical instead (no image tells them apart); their
    #: frames are listed in ``dataset.json`` (``twins``) so evaluations report them apart.
    identical_twins: int = 1
    #: Target share of each drive's frames (after the first) with no true match among earlier
    #: drives, by the ground truth above. 0: routes are plain walks preferring driven streets
    #: (``revisit``). Otherwise each drive's route is the first of :data:`ROUTE_CANDIDATES`
    #: seeded candidates that meets the targets (at least this share novel, ``reverse_fraction``
    #: the other way, :data:`MIN_MATCHED` known), or the one that misses them least.
    novel_fraction: float = 0.0
    #: Target share of frames on streets earlier drives drove only in the other direction (part
    #: of the novel share: the other way, a street looks different and has no match).
    reverse_fraction: float = 0.0
    #: Season of drive ``i``: ``seasons[i % len(seasons)]`` (names from
    #: :data:`~sprint_map.synth.seasons.SEASONS`), applied before its condition; ``()``: none.
    seasons: tuple[str, ...] = ()
    #: Scales every season's ground, sky and overlay blends (0: no visible season).
    season_strength: float = 0.6

    def __post_init__(self) -> None:
        if len(self.grid) != 2 or min(self.grid) < 2:
            raise ValueError("grid must be two integers >= 2")
        if not self.conditions or any(c not in CONDITIONS for c in self.conditions):
            raise ValueError(f"conditions must be names from {', '.join(CONDITIONS)}")
        if any(c not in SEASONS for c in self.seasons):
            raise ValueError(f"seasons must be names from {', '.join(SEASONS)}")
        if not 0 <= self.season_strength <= 2:
            raise ValueError("season_strength must be in [0, 2]")
        if self.speed_m <= 0 or self.detail < 0 or not 0 <= self.stop_prob <= 1:
            raise ValueError("speed_m must be > 0, detail >= 0, stop_prob in [0, 1]")
        if self.revisit <= 0:
            raise ValueError("revisit must be > 0")
        if not 0 <= self.alias_streets <= 0.5:
            raise ValueError("alias_streets must be in [0, 0.5]")
        if self.identical_twins < 0:
            raise ValueError("identical_twins must be >= 0")
        if not 0 <= self.reverse_fraction <= self.novel_fraction <= 1 - MIN_MATCHED:
            raise ValueError(
                f"need 0 <= reverse_fraction <= novel_fraction <= {1 - MIN_MATCHED}")
        Camera(self.width, self.height, self.fov_deg)  # validates the image parameters

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> CityConfig:
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


@dataclass(frozen=True)
class TraversalPlan:
    """Everything that determines one traversal before rendering."""

    index: int
    name: str
    condition: Condition
    trajectory: Trajectory
    camera_height_m: float
    pitch_px: float
    yaw_wobble_deg: float
    yaw_period_frames: float
    shake: float  # per-frame camera shake: yaw sd in degrees, pitch sd in pixels
    seed: tuple[int, ...]
    season: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            **({"season": self.season} if self.season else {}),
            "condition": self.condition.to_dict(),
            "route": [list(node) for node in self.trajectory.route],
            "camera_height_m": round(self.camera_height_m, 3),
            "pitch_px": round(self.pitch_px, 3),
            "yaw_wobble_deg": round(self.yaw_wobble_deg, 3),
        }


@dataclass
class SyntheticTraversal:
    """One rendered traversal, in memory.

    Attributes
    ----------
    name : str
    condition : str
        Preset name (the jittered parameters are in ``plan.condition``).
    images : ndarray of uint8, (N, H, W, 3) BGR
    positions : ndarray of float64, (N, 4)
        ``frame, x, y, heading_deg`` as :meth:`~sprint_map.frontend.positions.Positions.table`
        returns them.
    plan : TraversalPlan
    """

    name: str
    condition: str
    images: Image
    positions: Float64Array
    plan: TraversalPlan


@dataclass
class SyntheticCity:
    """A rendered city: traversals plus their ground truth."""

    config: CityConfig
    seed: int
    traversals: list[SyntheticTraversal] = field(default_factory=list)

    @property
    def names(self) -> list[str]:
        """Traversal names, in order."""
        return [t.name for t in self.traversals]

    def ground_truth(self) -> GroundTruth:
        """Position ground truth over the traversals (radius and heading from the config)."""
        positions = {t.name: t.positions for t in self.traversals}
        return GroundTruth(self.config.ground_truth_spec(), positions=positions)


class _World:
    """The city and the traversal plans, built once per generation."""

    def __init__(self, config: CityConfig, n_traversals: int, frames: int, seed: int) -> None:
        if n_traversals < 1 or frames < 1:
            raise ValueError("n_traversals and frames_per_traversal must be >= 1")
        self.config = config
        rng = np.random.default_rng([seed, 0])
        self.layout: CityLayout = build_layout(
            rng, config.grid[0], config.grid[1], config.block_m, config.street_m, config.n_styles,
            config.alias_streets, config.identical_twins,
        )
        self.atlas: Atlas = build_atlas(self.layout, rng, detail=config.detail)
        self.camera = Camera(config.width, config.height, config.fov_deg)
        #: One look per season used (its overlay is drawn once, from the world's seed).
        self.seasons = {name: SeasonLook(SEASONS[name], seed, config.season_strength)
                        for name in config.seasons}
        self.plans: list[TraversalPlan] = []
        driven: set[Edge] = set()
        for i in range(n_traversals):
            plan = self._plan(i, frames, seed, driven)
            route = plan.trajectory.route
            driven.update(zip(route[:-1], route[1:], strict=True))
            self.plans.append(plan)

    def _plan(self, i: int, frames: int, seed: int, driven: set[Edge]) -> TraversalPlan:
        config = self.config
        rng = np.random.default_rng([seed, 1, i])
        preset = config.conditions[i % len(config.conditions)]
        condition = CONDITIONS[preset].jittered(rng) if i else CONDITIONS[preset]
        params = Drive(
            speed_m=config.speed_m * float(rng.uniform(0.7, 1.3)),
            lane_m=float(rng.uniform(1.0, 3.0)),
            stop_prob=config.stop_prob,
        )
        # Steps never exceed 1.8x the mean speed; corners and lane offsets shorten the path a
        # little, hence the extra block.
        length = frames * params.speed_m * 1.8 + config.block_m
        if i and config.novel_fraction > 0:
            trajectory = self._novel_trajectory(i, frames, seed, driven, params, length)
        else:
            route: list[Node] = plan_route(self.layout, length, driven, rng, config.revisit)
            trajectory = drive(self.layout, route, frames, rng, params)
        season = config.season_of(i)
        return TraversalPlan(
            index=i,
            name=f"t{i:02d}-{preset}" + (f"-{season}" if season else ""),
            condition=condition,
            trajectory=trajectory,
            camera_height_m=float(rng.uniform(1.45, 1.75)),
            pitch_px=float(rng.uniform(-3, 3)) * config.height / 120,
            yaw_wobble_deg=float(rng.uniform(1.0, 4.0)),
            yaw_period_frames=float(rng.uniform(30, 90)),
            shake=config.shake,
            seed=(seed, 2, i),
            season=season,
        )

    def _novel_trajectory(
        self, i: int, frames: int, seed: int, driven: set[Edge], params: Drive, length: float
    ) -> Trajectory:
        """The first candidate route meeting the novelty targets, else the closest one."""
        config = self.config
        earlier = [plan.trajectory for plan in self.plans]
        earlier_xy = np.concatenate([t.xy for t in earlier])
        earlier_heading = np.concatenate([t.heading_deg for t in earlier])
        best: tuple[float, Trajectory] | None = None
        for c in range(ROUTE_CANDIDATES):
            rng = np.random.default_rng([seed, 3, i, c])
            route = plan_route(
                self.layout, length, driven, rng, config.revisit,
                new_weight=float(rng.uniform(1.0, 12.0)),
                reverse_weight=float(rng.uniform(0.5, 8.0)),
            )
            trajectory = drive(self.layout, route, frames, rng, params)
            matched, opposite = overlap(
                trajectory.xy, trajectory.heading_deg, earlier_xy, earlier_heading,
                config.radius_m, config.heading_deg,
            )
            shortfall = (
                4 * max(0.0, config.novel_fraction - (1 - matched.mean()))
                + 2 * max(0.0, config.reverse_fraction - opposite.mean())
                + max(0.0, MIN_MATCHED - matched.mean())
            )
            if best is None or shortfall < best[0]:
                best = (shortfall, trajectory)
            if shortfall == 0:
                break
        assert best is not None
        return best[1]

    def frames(self, plan: TraversalPlan) -> Iterator[Image]:
        """Render the traversal's images, in order."""
        renderer = Renderer(self.layout, self.atlas, self.camera)  # one per thread: it caches
        appearance = Appearance(plan.condition, np.random.default_rng(list(plan.seed)))
        shake = np.random.default_rng([*plan.seed, 1]).normal(
            0, plan.shake, (len(plan.trajectory.xy), 2)
        )
        phase = 2 * np.pi * (plan.index * 0.618)
        season = self.seasons[plan.season] if plan.season else None
        traj = plan.trajectory
        for k in range(len(traj.xy)):
            yaw = plan.yaw_wobble_deg * np.sin(2 * np.pi * k / plan.yaw_period_frames + phase)
            heading = float(traj.heading_deg[k]) + yaw + shake[k, 0]
            view = renderer.render(
                float(traj.xy[k, 0]),
                float(traj.xy[k, 1]),
                heading,
                height_m=plan.camera_height_m,
                pitch_px=plan.pitch_px + shake[k, 1] * self.config.height / 120,
                sky=plan.condition.sky,
            )
            if season is not None:
                view = season.apply(view)
            yield appearance.apply(view, heading)

    def traversal(self, plan: TraversalPlan) -> SyntheticTraversal:
        """Render one traversal into memory."""
        images = np.stack(list(self.frames(plan)))
        preset = self.config.conditions[plan.index % len(self.config.conditions)]
        return SyntheticTraversal(plan.name, preset, images, self.positions(plan), plan)

    @staticmethod
    def positions(plan: TraversalPlan) -> Float64Array:
        traj = plan.trajectory
        frames = np.arange(len(traj.xy), dtype=np.float64)
        return np.column_stack([frames, traj.xy, traj.heading_deg])


#: The demo's worlds (``sprint-map demo --dataset NAME``). ``city``: routes that mostly revisit,
#: four facade styles. ``city-novel``: a larger grid where every traversal after the first
#: spends at least 60 % of its frames where no earlier one was (10 % on streets driven the
#: other way), three facade styles and a quarter of the streets copies of others.
PRESETS: dict[str, CityConfig] = {
    "city": CityConfig(),
    "city-novel": CityConfig(
        grid=(5, 5), n_styles=3, alias_streets=0.25, novel_fraction=0.6, reverse_fraction=0.1
    ),
}


def iter_city(
    n_traversals: int = 6,
    frames_per_traversal: int = 300,
    seed: int = 0,
    config: CityConfig | None = None,
    workers: int | None = None,
) -> Iterator[SyntheticTraversal]:
    """Render a synthetic city one traversal at a time, in order (same output as
    :func:`render_city`).

    At most ``workers`` traversals are rendered ahead of the consumer, so memory is bounded
    by ``workers + 1`` traversals whatever ``n_traversals`` is.

    Yields
    ------
    SyntheticTraversal
    """
    config = config or CityConfig()
    world = _World(config, n_traversals, frames_per_traversal, seed)
    workers = workers or default_workers()
    with ThreadPoolExecutor(max_workers=workers) as pool:
        pending: deque[Any] = deque()
        for plan in world.plans:
            pending.append(pool.submit(world.traversal, plan))
            if len(pending) > workers:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


def render_city(
    n_traversals: int = 6,
    frames_per_traversal: int = 300,
    seed: int = 0,
    config: CityConfig | None = None,
    workers: int | None = None,
) -> SyntheticCity:
    """Render a synthetic city in memory.

    Parameters
    ----------
    n_traversals : int
    frames_per_traversal : int
        Frames of every traversal.
    seed : int
    config : CityConfig, optional
    workers : int, optional
        Traversals rendered in parallel (threads); default: available cores.

    Returns
    -------
    SyntheticCity
        Memory: ``n_traversals * frames * width * height * 3`` bytes of images (100 MB for the
        defaults); use :func:`generate_city` for large sets.
    """
    config = config or CityConfig()
    world = _World(config, n_traversals, frames_per_traversal, seed)
    with ThreadPoolExecutor(max_workers=workers or default_workers()) as pool:
        traversals = list(pool.map(world.traversal, world.plans))
    return SyntheticCity(config, seed, traversals)


def generate_city(
    out_dir: str | Path,
    n_traversals: int = 6,
    frames_per_traversal: int = 300,
    seed: int = 0,
    config: CityConfig | None = None,
    image_format: str = "png",
    workers: int | None = None,
) -> Path:
    """Write a synthetic city data set to ``out_dir`` and return ``out_dir``.

    Layout::

        out_dir/dataset.json               {"alignment": "position", "radius_m": ..., ...,
                                            "twins": {traversal: [[start, stop), ...]]}}
        out_dir/t00-day/000000.png ...     the images
        out_dir/t00-day/positions.csv      frame,x,y,heading_deg
        out_dir/t01-overcast/ ...

    The set is written to a hidden sibling directory and renamed into place at the end, so an
    interrupted run never leaves a half-written data set. ``out_dir`` must not exist or be an
    empty directory (else :class:`InputError`); ``n_traversals`` (drives),
    ``frames_per_traversal``, ``seed``, ``config`` and ``workers`` are as for
    :func:`render_city`; ``image_format``: ``"png"`` (lossless, deterministic) or ``"jpg"``
    (quality 90, ~3x smaller; anything else: :class:`ConfigError`).
    """
    out = Path(out_dir)
    if image_format not in IMAGE_FORMATS:
        raise ConfigError(f"image_format must be one of {', '.join(IMAGE_FORMATS)}")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(f"{out}: exists and is not an empty directory")
    config = config or CityConfig()
    world = _World(config, n_traversals, frames_per_traversal, seed)
    staging = out.parent / f".{out.name}.partial-{os.getpid()}"
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    params = [cv2.IMWRITE_JPEG_QUALITY, 90] if image_format == "jpg" else []

    def one(plan: TraversalPlan) -> None:
        folder = staging / plan.name
        folder.mkdir()
        for k, image in enumerate(world.frames(plan)):
            path = folder / f"{k:06d}.{image_format}"
            if not cv2.imwrite(str(path), image, params):
                raise OSError(f"{path}: cannot write image")
        rows = world.positions(plan)
        with (folder / "positions.csv").open("w", encoding="utf-8") as handle:
            handle.write("frame,x,y,heading_deg\n")
            for frame, x, y, heading in rows:
                handle.write(f"{int(frame)},{x:.3f},{y:.3f},{heading:.2f}\n")

    try:
        with ThreadPoolExecutor(max_workers=workers or default_workers()) as pool:
            list(pool.map(one, world.plans))
        twins = ({"twins": {plan.name: frame_ranges(world.layout.on_twin(plan.trajectory.xy))
                            for plan in world.plans}} if world.layout.twins else {})
        description = {
            **config.ground_truth_spec().to_dict(),
            "description": (
                f"Synthetic city (sprint_map.synth), {n_traversals} traversals x "
                f"{frames_per_traversal} frames, seed {seed}"
            ),
            **twins,
            "generator": {
                "module": "sprint_map.synth.city",
                "seed": seed,
                "frames_per_traversal": frames_per_traversal,
                "config": config.to_dict(),
                "traversals": [plan.to_dict() for plan in world.plans],
                "twin_streets": [[list(a), list(b)] for a, b in world.layout.twins],
            },
        }
        (staging / "dataset.json").write_text(json.dumps(description, indent=2) + "\n")
        if out.exists():
            out.rmdir()  # empty, checked above
        os.replace(staging, out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return out
