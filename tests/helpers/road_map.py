"""A small generated map for the trace and viewer tests: drives over one road, with positions.

``build_road_map`` ingests ``drives`` traversals of a 200-place road (each under its own
appearance change, at a varying speed, with its positions along the road), so the later drives
merge with the earlier ones, plus one drive of a separate road that matches nothing (its own
component). ``drive`` makes another traversal (a query for ``localize``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sprint_map.config import MapConfig
from sprint_map.map import SprintMap
from tests.helpers.worlds import road_places, traverse

__all__ = ["DIM", "Road", "RoadMap", "build_road_map", "thumbnails"]

DIM = 32
PLACES = 200


@dataclass
class Road:
    """Appearance and position of each place of a road."""

    appearance: np.ndarray  # (PLACES, DIM)
    xy: np.ndarray  # (PLACES, 2) metres

    @classmethod
    def make(cls, rng: np.random.Generator, origin: tuple[float, float] = (0.0, 0.0)) -> Road:
        places = road_places(rng, PLACES, DIM, corr=0.9)
        t = np.arange(PLACES) * 5.0  # a place every 5 m along a bend
        xy = np.c_[origin[0] + t, origin[1] + 200 * np.sin(t / 300)]
        return cls(places, xy)

    def drive(self, rng: np.random.Generator, frames: int, start: int = 0,
              noise: float = 0.6) -> tuple[np.ndarray, np.ndarray]:
        """``(descriptors, positions)`` of a traversal from place ``start``."""
        desc, idx = traverse(rng, self.appearance, start, frames, noise, speed=(0.8, 1.2))
        return desc, self.xy[idx] + rng.normal(0, 0.5, (frames, 2))


@dataclass
class RoadMap:
    """A map built by :func:`build_road_map` (closed): its path, road and sequence ids."""

    path: Path
    road: Road
    ids: list[int]


def thumbnails(xy: np.ndarray) -> list[bytes]:
    """A small JPEG per frame, its colour following the frame's position."""
    import cv2

    out = []
    for x, y in xy:
        img = np.zeros((48, 64, 3), np.uint8)
        img[:] = (int(x) % 256, int(y) % 256, 128)
        cv2.circle(img, (32, 24), 10, (255, 255, 255), -1)
        out.append(cv2.imencode(".jpg", img)[1].tobytes())
    return out


def build_road_map(path: Path, rng: np.random.Generator, drives: int = 4,
                   frames: int = 150, *, with_thumbnails: bool = False
                   ) -> tuple[Road, list[int]]:
    """Create the map at ``path``; return the road and the sequence ids, in order."""
    road = Road.make(rng)
    other = Road.make(rng, origin=(0.0, 600.0))
    ids = []
    with SprintMap.create(path, MapConfig(dim=DIM)) as m:
        for i in range(drives + 1):
            desc, xy = road.drive(rng, frames, start=5 * i) if i < drives else \
                other.drive(rng, frames)
            ids.append(m.ingest(desc, name=f"drive-{i}" if i < drives else "elsewhere",
                                positions=xy,
                                thumbnails=thumbnails(xy) if with_thumbnails else None
                                ).added.sequence.seq_id)
    return road, ids
