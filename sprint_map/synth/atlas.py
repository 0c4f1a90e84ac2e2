"""The texture atlas of a city: every building front, the skyline and a map of the ground.

All textures live in one BGR image so that a whole camera view is a single ``cv2.remap`` (about
0.5 ms for a 320x240 view). Building fronts are shelf-packed below the ground map with a gap of
a few texels, so bilinear sampling never bleeds one texture into another.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from sprint_map.synth.layout import CityLayout
from sprint_map.synth.textures import draw_facade, draw_skyline

__all__ = ["Atlas", "build_atlas", "draw_ground"]

_GAP = 2  # texels between packed textures
_MAX_SIDE = 32000  # cv2.remap coordinates must stay below SHRT_MAX


@dataclass(frozen=True)
class Atlas:
    """Packed textures and where each one is.

    Attributes
    ----------
    image : ndarray of uint8, (H, W, 3)
    rects : ndarray of float64, (n_buildings, 4)
        ``x0, y0, width, height`` in texels of building ``i``'s texture.
    px_per_m : float
        Facade texture resolution.
    ground_px_per_m : float
        Ground map resolution; the ground map's texel (0, 0) is the world's (xmin, ymax).
    """

    image: np.ndarray
    rects: np.ndarray
    px_per_m: float
    ground_px_per_m: float
    ground_shape: tuple[int, int]


def build_atlas(
    layout: CityLayout,
    rng: np.random.Generator,
    px_per_m: float = 8.0,
    ground_px_per_m: float = 4.0,
    detail: float = 1.0,
) -> Atlas:
    """Draw and pack every texture of ``layout``.

    Cost: dominated by drawing the facades, ~2 ms per building (~0.8 s for the default 4 x 4
    city of ~320 buildings). A building with a ``twin`` (an aliased street) is not drawn: it
    samples its twin's texture.
    """
    ground = draw_ground(layout, rng, ground_px_per_m)
    textures: list[np.ndarray] = []
    for building in layout.buildings:
        if building.twin >= 0:  # a copy of another street: that building's texture, again
            textures.append(textures[building.twin])
            continue
        if building.style < 0:
            tex = draw_skyline(building.length_m, building.height_m, px_per_m / 4, rng)
        else:
            tex = draw_facade(
                layout.styles[building.style],
                building.length_m,
                building.height_m,
                px_per_m,
                rng,
                detail,
            )
        textures.append(tex)

    width = max(4096, ground.shape[1])
    positions: list[tuple[int, int]] = []
    x, y, shelf = 0, ground.shape[0] + _GAP, 0
    for i, tex in enumerate(textures):
        twin = layout.buildings[i].twin
        if twin >= 0:
            positions.append(positions[twin])  # drawn once, sampled by both
            continue
        h, w = tex.shape[:2]
        if w > width:
            raise ValueError("a texture is wider than the atlas")
        if x + w > width:
            x, y, shelf = 0, y + shelf + _GAP, 0
        positions.append((x, y))
        x += w + _GAP
        shelf = max(shelf, h)
    height = y + shelf
    if height > _MAX_SIDE:
        raise ValueError("city too large for one texture atlas; use a smaller grid")
    image = np.zeros((height, width, 3), dtype=np.uint8)
    image[: ground.shape[0], : ground.shape[1]] = ground
    rects = np.empty((len(textures), 4), dtype=np.float64)
    for i, (tex, (tx, ty)) in enumerate(zip(textures, positions, strict=True)):
        h, w = tex.shape[:2]
        image[ty : ty + h, tx : tx + w] = tex
        rects[i] = (tx, ty, w, h)
    return Atlas(image, rects, px_per_m, ground_px_per_m, (ground.shape[0], ground.shape[1]))


def draw_ground(layout: CityLayout, rng: np.random.Generator, px_per_m: float) -> np.ndarray:
    """Top-down map of the ground: asphalt, sidewalks, lane markings, crossings, patches."""
    xmin, ymin, xmax, ymax = layout.extent
    w, h = round((xmax - xmin) * px_per_m), round((ymax - ymin) * px_per_m)

    def px(x: float, y: float) -> tuple[int, int]:
        return round((x - xmin) * px_per_m), round((ymax - y) * px_per_m)

    img = np.empty((h, w, 3), dtype=np.uint8)
    img[:] = (78, 80, 82)
    for _ in range(int(w * h / 4000)):  # asphalt repairs
        x, y = rng.uniform(xmin, xmax), rng.uniform(ymin, ymax)
        a, b = rng.uniform(0.5, 4.0, size=2)
        shade = int(rng.integers(50, 100))
        cv2.rectangle(img, px(x, y), px(x + a, y - b), (shade, shade, shade + 2), -1)
    half, sidewalk, block = layout.street_m / 2, 3.0, layout.block_m
    for bj in range(-1, layout.ny):
        for bi in range(-1, layout.nx):
            x0, x1 = bi * block + half - sidewalk, (bi + 1) * block - half + sidewalk
            y0, y1 = bj * block + half - sidewalk, (bj + 1) * block - half + sidewalk
            cv2.rectangle(img, px(x0, y1), px(x1, y0), (150, 152, 155), -1)
            # Paving joints every 1.5 m: gives the ground texture that moves with the camera.
            for x in np.arange(x0, x1, 1.5):
                cv2.line(img, px(x, y0), px(x, y1), (125, 127, 130), 1)
            for y in np.arange(y0, y1, 1.5):
                cv2.line(img, px(x0, y), px(x1, y), (125, 127, 130), 1)
            cv2.rectangle(img, px(x0, y1), px(x1, y0), (110, 110, 110), 2)  # kerb
    white = (215, 215, 215)
    for j in range(layout.ny):
        for i in range(layout.nx):
            cx, cy = i * block, j * block
            for dx, dy in ((1, 0), (0, 1)):
                if i + dx >= layout.nx or j + dy >= layout.ny:
                    continue
                # Dashed centre line from one crossing to the next.
                for t in np.arange(half + 4.0, block - half - 4.0, 6.0):
                    a = (cx + dx * t, cy + dy * t)
                    b = (cx + dx * (t + 3.0), cy + dy * (t + 3.0))
                    cv2.line(img, px(*a), px(*b), white, max(1, round(0.15 * px_per_m)))
            # Zebra crossings on the four approaches.
            for dx, dy in ((1, 0), (0, 1), (-1, 0), (0, -1)):
                base, road_half = half + 1.5, half - sidewalk
                for k in np.arange(-road_half + 0.5, road_half, 1.0):
                    ox, oy = cx + dx * base - dy * k, cy + dy * base + dx * k
                    a = (ox - dx * 1.2, oy - dy * 1.2)
                    b = (ox + dx * 1.2, oy + dy * 1.2)
                    cv2.line(img, px(*a), px(*b), white, max(1, round(0.4 * px_per_m)))
    noise = rng.normal(0, 6, (h, w, 1))
    return np.clip(img + noise, 0, 255).astype(np.uint8)
