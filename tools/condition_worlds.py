"""The drive streams of :mod:`tools.bench_conditions`: generated worlds with seasons and the cut of
Nordland, each as drives in stream order plus held-back *probe* drives, never merged.

- ``latent``: :mod:`sprint_map.synth.latent` with seasons (:data:`SEASON_CYCLE` in turn) over its
  six conditions; 40 % of each drive's frames on streets no earlier drive saw;
- ``city``: :mod:`sprint_map.synth.city`, rendered and described by HoG, with seasons
  (:mod:`sprint_map.synth.seasons`) over four conditions in turn;
- ``nordland``: the real ride cut into segments; each drive is 2-4 consecutive segments of one
  season (drawn from the seed), its images under its own exposure (gamma U(0.7, 1.4)) and
  sensor noise (sigma U(2, 6) grey levels) before HoG; true match within +/- 1 frame of the
  ride.

The probes of a generated world are its next drives after the stream (one cycle of the
seasons by default); Nordland's alternate summer and winter, drawn from a stream of their own so
the stream's drives do not depend on how many probes there are.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map import MapConfig
from sprint_map.frontend import GroundTruth, GroundTruthSpec
from sprint_map.synth.latent import LatentConfig, make_latent

__all__ = ["CITY_CONDITIONS", "Drive", "GAMMA", "LATENT", "NOISE", "SEASON_CYCLE", "World",
           "city_world", "default_nordland", "latent_world", "nordland_world"]

#: The seasons in turn over the drives of the generated worlds.
SEASON_CYCLE = ("summer", "summer", "winter", "winter")
LATENT = LatentConfig(grid=(5, 5), novel_fraction=0.4, reverse_fraction=0.05,
                      seasons=SEASON_CYCLE)
#: The city's conditions (one per drive in turn) under the seasons.
CITY_CONDITIONS = ("day", "overcast", "dusk", "rain")
#: The issue's exposure and noise ranges of a Nordland drive.
GAMMA = (0.7, 1.4)
NOISE = (2.0, 6.0)


@dataclasses.dataclass
class Drive:
    """One drive of the stream: its descriptors and what it was driven under."""

    name: str
    season: str
    condition: str
    rows: np.ndarray  # (N, dim) float32


@dataclasses.dataclass
class World:
    """Drives in stream order, their ground truth, and the map config they fit."""

    name: str
    drives: list[Drive]
    gt: GroundTruth
    config: MapConfig
    about: dict[str, Any]
    #: Held-back drives: answered by the map at the stream's half and at its end, never merged.
    probes: list[Drive] = dataclasses.field(default_factory=list)


def latent_world(seed: int, drives: int, frames: int, strength: float | None,
                 probes: int = 0) -> World:
    """The latent family with seasons (``strength``: override of ``season_strength``); the
    ``probes`` drives after the stream's are held back."""
    config = LATENT if strength is None else dataclasses.replace(LATENT, season_strength=strength)
    world = make_latent(drives + probes, frames, seed, config)
    out = [Drive(t.name, t.season or "-", t.condition, t.descriptors) for t in world.traversals]
    return World("latent", out[:drives], world.ground_truth(), MapConfig(dim=config.dim),
                 {"config": config.to_dict()}, out[drives:])


def city_world(seed: int, drives: int, frames: int, strength: float | None,
               probes: int = 0) -> World:
    """The rendered city with seasons, described by HoG (``strength``: of the seasons); the
    ``probes`` drives after the stream's are held back."""
    from sprint_map.synth import CityConfig, iter_city

    config = CityConfig(grid=(4, 4), novel_fraction=0.4, reverse_fraction=0.05,
                        conditions=CITY_CONDITIONS, seasons=SEASON_CYCLE)
    if strength is not None:
        config = dataclasses.replace(config, season_strength=strength)
    map_config = MapConfig.for_descriptor("hog")
    spec = map_config.descriptor_spec()
    assert spec is not None
    out, positions = [], {}
    for t in iter_city(drives + probes, frames, seed=seed, config=config, workers=2):
        out.append(Drive(t.name, t.plan.season or "-", t.condition, spec.describe_batch(t.images)))
        positions[t.name] = t.positions
    gt = GroundTruth(config.ground_truth_spec(), positions=positions)
    return World("city", out[:drives], gt, map_config, {"config": config.to_dict()},
                 out[drives:])


def nordland_world(seed: int, root: Path, frames: int, segments: int, drives: int,
                   probes: int = 0) -> World:
    """The cut of Nordland: the first ``frames`` frames of the ride in ``segments`` equal
    segments; each drive 2-4 consecutive segments of one season, its images under its own gamma
    and sensor noise, then HoG; ``probes`` held-back drives more, summer and winter in turn.
    Ground truth: the ride's frame index, +/- 1 frame."""
    import cv2

    map_config = MapConfig.for_descriptor("hog")
    spec = map_config.descriptor_spec()
    assert spec is not None
    files = sorted((root / "summer").glob("*.png"))[:frames]
    if not files:
        raise SystemExit(f"{root}: no summer/*.png (Nordland not found; pass --nordland)")
    images = {}
    for season in ("summer", "winter"):
        frames_read = []
        for f in files:
            image = cv2.imread(str(root / season / f.name))
            if image is None:
                raise SystemExit(f"{root / season / f.name}: cannot read the image")
            frames_read.append(image)
        images[season] = np.stack(frames_read)
    bounds = np.linspace(0, len(files), segments + 1).round().astype(int)
    out, positions, about = [], {}, []
    stream, held = np.random.default_rng([seed, 51]), np.random.default_rng([seed, 52])
    for i in range(drives + probes):
        rng = stream if i < drives else held
        length = int(rng.integers(2, 5))
        first = int(rng.integers(0, segments - length + 1))
        season = (("summer", "winter")[int(rng.integers(2))] if i < drives
                  else ("summer", "winter")[(i - drives) % 2])
        gamma, sigma = float(rng.uniform(*GAMMA)), float(rng.uniform(*NOISE))
        ride = np.arange(bounds[first], bounds[first + length])
        levels = 255.0 * (np.arange(256) / 255.0) ** gamma
        shot = levels[images[season][ride]] + rng.normal(0, sigma, images[season][ride].shape)
        pictures = np.clip(shot, 0, 255).astype(np.uint8)
        name = f"d{i:02d}-{season}" if i < drives else f"p{i - drives:02d}-{season}"
        out.append(Drive(name, season, f"g{gamma:.2f}/n{sigma:.1f}", spec.describe_batch(pictures)))
        positions[name] = np.column_stack([np.arange(len(ride)), ride, np.zeros(len(ride))])
        about.append({"name": name, "season": season, "segments": [first, first + length],
                      "ride_frames": [int(ride[0]), int(ride[-1]) + 1],
                      "gamma": round(gamma, 3), "noise": round(sigma, 2)})
    gt = GroundTruth(GroundTruthSpec("position", radius_m=1.0), positions=positions)
    return World("nordland", out[:drives], gt, map_config,
                 {"root": str(root), "frames": len(files), "segments": segments,
                  "drives": about[:drives], "probes": about[drives:]}, out[drives:])


def default_nordland() -> Path | None:
    """Where the Nordland set is: :func:`~sprint_map.evaluation.demo.find_nordland`'s places
    (``$SPRINT_MAP_NORDLAND`` first), else ``shared/data/nordland`` beside a parent of this
    checkout."""
    from sprint_map.evaluation.demo import find_nordland

    found = find_nordland()
    if found is not None:
        return found
    for parent in Path(__file__).resolve().parents:
        if (parent / "shared" / "data" / "nordland" / "summer").is_dir():
            return parent / "shared" / "data" / "nordland"
    return None


