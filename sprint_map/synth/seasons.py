"""Seasons of the synthetic city: a change of the whole scene shared by every drive of a season.

A condition (:mod:`.conditions`) is jittered per drive and much of it (traffic, rain, flakes,
noise) changes from frame to frame. A season is the opposite: what a global descriptor sees of
it is the *same* in every frame of every drive of that season, so it is a shared component of
their descriptors, as snow is in Nordland's winter (a winter query is pulled towards every winter
drive the map holds, wherever it was driven). :class:`SeasonLook` applies one to rendered views,
before the drive's condition:

- the ground is blended towards the season's ground colour (snow, or green verges);
- the sky towards the season's sky;
- a fixed overlay is laid over every frame, drawn once per world and season from the world's seed:
  snowbanks along both sides of the road in winter, overhanging foliage at the top corners and
  grass along the bottom in summer; it sits at the same image position in every frame, so HoG
  sees the same gradients in every frame of the season.

``strength`` scales all three (0: the view unchanged). Everything derives from the world's seed
and the season's name; nothing here draws from a drive's generator, so a world without seasons is
bit-identical to one rendered before seasons existed.

Cost: the overlay is drawn once per (season, image size), ~1 ms; applying it is three blends of
the frame, ~0.3 ms at 160x120.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np

from sprint_map.synth.render import BGR, View

__all__ = ["SEASONS", "Season", "SeasonLook"]


@dataclass(frozen=True)
class Season:
    """What a season changes (colours BGR; shares in [0, 1] at strength 1)."""

    name: str
    ground: BGR  # colour the ground is blended towards
    ground_share: float
    sky: BGR  # colour the sky is blended towards
    sky_share: float
    overlay: str  # "snowbanks" or "foliage"
    overlay_alpha: float


#: The seasons, by name (index = the seed stream of the season's overlay).
SEASONS: dict[str, Season] = {
    s.name: s
    for s in (
        Season("summer", ground=(60, 120, 70), ground_share=0.35, sky=(235, 190, 140),
               sky_share=0.4, overlay="foliage", overlay_alpha=0.9),
        Season("winter", ground=(245, 245, 245), ground_share=0.85, sky=(225, 222, 220),
               sky_share=0.7, overlay="snowbanks", overlay_alpha=0.95),
    )
}


class SeasonLook:
    """One season of one world applied to views of a given size.

    Parameters
    ----------
    season : Season
    seed : int
        The world's seed: the overlay is drawn from ``(seed, 20, index of the season)``.
    strength : float
        Scales the ground, sky and overlay blends (clipped to 1 each).
    """

    def __init__(self, season: Season, seed: int, strength: float) -> None:
        self.season = season
        self.seed = seed
        self.strength = strength
        self._overlay: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def apply(self, view: View) -> View:
        """The view under this season (a new View; depth and masks unchanged)."""
        s, k = self.season, self.strength
        h, w = view.image.shape[:2]
        img = view.image.astype(np.float32)
        ground = min(1.0, s.ground_share * k) * view.ground[:, :, None]
        img += ground * (np.array(s.ground, dtype=np.float32) - img)
        sky = min(1.0, s.sky_share * k) * view.sky[:, :, None]
        img += sky * (np.array(s.sky, dtype=np.float32) - img)
        colour, alpha = self.overlay(h, w)
        img += (min(1.0, k) * alpha) * (colour - img)
        out = np.clip(img, 0, 255, out=img).astype(np.uint8)
        return dataclasses.replace(view, image=out)

    def overlay(self, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
        """The season's fixed overlay for ``h x w`` frames: colour (H, W, 3) float32 and
        alpha (H, W, 1) float32 in [0, overlay_alpha]; drawn once per size."""
        cached = self._overlay.get((h, w))
        if cached is None:
            rng = np.random.default_rng([self.seed, 20, list(SEASONS).index(self.season.name)])
            draw = _snowbanks if self.season.overlay == "snowbanks" else _foliage
            colour, mask = draw(h, w, rng)
            soft = cv2.GaussianBlur(mask, (0, 0), max(0.6, w / 200))
            cached = (colour, (self.season.overlay_alpha * soft)[:, :, None])
            self._overlay[(h, w)] = cached
        return cached


def _smooth_curve(rng: np.random.Generator, n: int, knots: int) -> np.ndarray:
    """A smooth random curve of ``n`` samples in about [-1, 1] (cubic through ``knots``)."""
    values = rng.uniform(-1, 1, knots).astype(np.float32)[None, :]
    curve: np.ndarray = cv2.resize(values, (n, 1), interpolation=cv2.INTER_CUBIC)[0]
    return curve


def _snowbanks(h: int, w: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Snowbanks along both sides of the road: high at the image's sides, low in the middle,
    with a lumpy top edge; white with a little fixed texture."""
    x = np.arange(w, dtype=np.float32) / (w - 1)
    rise = np.abs(x - 0.5) * 2  # 0 in the middle, 1 at the sides
    top = h * (0.93 - 0.3 * rise ** 1.5 + 0.035 * _smooth_curve(rng, w, 14))
    rows = np.arange(h, dtype=np.float32)[:, None]
    mask = (rows >= top[None, :]).astype(np.float32)
    texture = rng.normal(0, 6, (h, w, 1)).astype(np.float32)
    shade = 238 - 25 * np.clip((rows - top[None, :]) / (0.15 * h), 0, 1)[:, :, None]
    colour = np.broadcast_to(shade, (h, w, 3)) + texture
    # A darker rim where the bank meets the road: a strong, fixed edge.
    rim = (np.abs(rows - top[None, :]) < max(1.0, h / 60)).astype(np.float32)[:, :, None]
    colour = colour * (1 - 0.35 * rim)
    return np.ascontiguousarray(colour, dtype=np.float32), mask


def _foliage(h: int, w: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Overhanging foliage at the top corners and tall grass along the bottom sides: dark
    greens, clumps of leaves."""
    mask = np.zeros((h, w), dtype=np.float32)
    colour = np.zeros((h, w, 3), dtype=np.float32)
    for _ in range(int(rng.integers(40, 60))):
        side = rng.integers(2)
        cx = float(rng.uniform(0, 0.3) * w) if side == 0 else float(rng.uniform(0.7, 1.0) * w)
        cy = float(rng.uniform(0, 0.3) * h)
        r = max(2, round(rng.uniform(0.03, 0.08) * w))
        green = (float(rng.integers(20, 60)), float(rng.integers(70, 150)), float(rng.integers(20, 70)))
        cv2.circle(mask, (round(cx), round(cy)), r, 1.0, -1)
        cv2.circle(colour, (round(cx), round(cy)), r, green, -1)
    x = np.arange(w, dtype=np.float32) / (w - 1)
    rise = np.abs(x - 0.5) * 2
    top = h * (1.0 - 0.18 * rise ** 2 + 0.03 * _smooth_curve(rng, w, 30))
    rows = np.arange(h, dtype=np.float32)[:, None]
    grass = rows >= top[None, :]
    mask[grass] = 1.0
    colour[grass] = (40.0, 110.0, 60.0)
    colour += rng.normal(0, 8, (h, w, 1)).astype(np.float32)
    return colour, mask
