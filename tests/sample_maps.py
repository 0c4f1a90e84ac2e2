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

__all__ = ["DIM", "Road", "build_road_map", "thumbnails"]

DIM = 32
PLACES = 200


def unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


@dataclass
class Road:
    """Appearance and position of each place of a road."""

    appearance: np.ndarray  # (PLACES, DIM)
    xy: np.ndarray  # (PLACES, 2) metres

    @classmethod
    def make(cls, rng: np.random.Generator, origin: tuple[float, float] = (0.0, 0.0)) -> Road:
        cur = unit(rng.standard_normal(DIM))
        places = []
        for _ in range(PLACES):
            cur = unit(0.9 * cur + np.sqrt(1 - 0.9**2) * unit(rng.standard_normal(DIM)))
            places.append(cur)
        t = np.arange(PLACES) * 5.0  # a place every 5 m along a bend
        xy = np.c_[origin[0] + t, origin[1] + 200 * np.sin(t / 300)]
        return cls(np.array(places), xy)

    def drive(self, rng: np.random.Generator, frames: int, start: int = 0,
              noise: float = 0.6) -> tuple[np.ndarray, np.ndarray]:
        """``(descriptors, positions)`` of a traversal from place ``start``."""
        pos = start + np.cumsum(rng.uniform(0.8, 1.2, frames)) - 1
        idx = np.clip(pos.astype(int), 0, PLACES - 1)
        shift = unit(rng.standard_normal(DIM)) * 0.3
        desc = unit(self.appearance[idx] + shift + noise * unit(rng.standard_normal((frames, DIM))))
        return desc, self.xy[idx] + rng.normal(0, 0.5, (frames, 2))


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
