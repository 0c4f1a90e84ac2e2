"""Synthetic places and drives over them: unit-norm float32 descriptors, no images.

A *road* is a chain of places whose appearance varies smoothly (each place correlated with
the previous one, like consecutive video frames: neighbours look alike); *random places* are
independent. A drive over places is each place's appearance plus noise; a *traversal* also
drives at a varying speed under its own appearance change (light, weather).
"""

from __future__ import annotations

import numpy as np

__all__ = ["drive", "random_places", "road_places", "traverse", "unit"]


def unit(x: np.ndarray) -> np.ndarray:
    """``x``'s rows scaled to unit norm, as float32."""
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def road_places(rng: np.random.Generator, n: int, dim: int, corr: float) -> np.ndarray:
    """``n`` places along a road, each correlated ``corr`` with the one before it."""
    cur = unit(rng.standard_normal(dim))
    places = []
    for _ in range(n):
        cur = unit(corr * cur + np.sqrt(1 - corr**2) * unit(rng.standard_normal(dim)))
        places.append(cur)
    return np.array(places)


def random_places(rng: np.random.Generator, n: int, dim: int) -> np.ndarray:
    """``n`` independent places."""
    return unit(rng.standard_normal((n, dim)))


def drive(places: np.ndarray, rng: np.random.Generator, noise: float = 0.3) -> np.ndarray:
    """A noisy drive over ``places``, one frame per place."""
    return unit(places + noise * rng.standard_normal(places.shape))


def traverse(rng: np.random.Generator, places: np.ndarray, start: int, frames: int,
             noise: float, speed: tuple[float, float] = (0.8, 1.25)
             ) -> tuple[np.ndarray, np.ndarray]:
    """``(descriptors, place index of each frame)`` of a drive from place ``start`` at a
    speed drawn per frame from ``speed`` (places per frame), under its own appearance change."""
    pos = start + np.cumsum(rng.uniform(*speed, frames)) - 1
    idx = np.clip(pos.astype(int), 0, len(places) - 1)
    shift = unit(rng.standard_normal(places.shape[1])) * 0.3
    noisy = noise * unit(rng.standard_normal((frames, places.shape[1])))
    return unit(places[idx] + shift + noisy), idx
