"""Geometry of the synthetic city: a grid of streets between square blocks of buildings.

Intersections sit at ``(i * block_m, j * block_m)`` for ``0 <= i < nx``, ``0 <= j < ny``; streets
of width ``street_m`` (sidewalks included) join neighbouring intersections. Each city block is a
solid square whose four sides are split into building fronts ("walls") of 8-20 m, and a ring of
blocks around the grid gives every street buildings on both sides. Four tall, distant walls with
a skyline close the world off, so every camera ray hits something.

Each block *side* gets one facade style from a small shared pool, so whole street sides resemble
other street sides elsewhere (perceptual aliasing); buildings within a side vary in height and
details. Coordinates are metres, x east, y north; headings are degrees counter-clockwise from +x.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sprint_map.synth.textures import FacadeStyle, random_style

Node = tuple[int, int]


@dataclass(frozen=True)
class Building:
    """One wall: a building front, seen from the street it faces.

    ``p0`` is the left end as seen by a viewer facing the front, so texture columns run
    left-to-right from ``p0`` to ``p1``.
    """

    p0: tuple[float, float]
    p1: tuple[float, float]
    height_m: float
    style: int  # index into CityLayout.styles, or -1 for the skyline walls
    side: int  # index of the block side (street side) it belongs to, -1 for the skyline

    @property
    def length_m(self) -> float:
        return float(np.hypot(self.p1[0] - self.p0[0], self.p1[1] - self.p0[1]))


@dataclass(frozen=True)
class CityLayout:
    """Street grid, buildings and facade styles."""

    nx: int
    ny: int
    block_m: float
    street_m: float
    styles: tuple[FacadeStyle, ...]
    buildings: tuple[Building, ...]
    extent: tuple[float, float, float, float]  # xmin, ymin, xmax, ymax of the closed world

    def node_xy(self, node: Node) -> np.ndarray:
        """Position of an intersection."""
        return np.array([node[0] * self.block_m, node[1] * self.block_m], dtype=np.float64)

    def neighbours(self, node: Node) -> list[Node]:
        """Intersections joined to ``node`` by a street, in a fixed order (E, N, W, S)."""
        i, j = node
        out = []
        for di, dj in ((1, 0), (0, 1), (-1, 0), (0, -1)):
            if 0 <= i + di < self.nx and 0 <= j + dj < self.ny:
                out.append((i + di, j + dj))
        return out

    @property
    def nodes(self) -> list[Node]:
        """All intersections."""
        return [(i, j) for j in range(self.ny) for i in range(self.nx)]


def build_layout(
    rng: np.random.Generator,
    nx: int = 4,
    ny: int = 4,
    block_m: float = 60.0,
    street_m: float = 14.0,
    n_styles: int = 6,
) -> CityLayout:
    """Lay out a city.

    Parameters
    ----------
    rng : numpy.random.Generator
    nx, ny : int
        Intersections per row / column (at least 2 each).
    block_m : float
        Distance between neighbouring intersections.
    street_m : float
        Street width between facades.
    n_styles : int
        Size of the shared facade-style pool; fewer styles, more aliasing.
    """
    if nx < 2 or ny < 2:
        raise ValueError("the grid needs at least 2 x 2 intersections")
    if not 0 < street_m < block_m / 2:
        raise ValueError("street_m must be positive and less than half of block_m")
    if n_styles < 1:
        raise ValueError("n_styles must be >= 1")
    styles = tuple(random_style(rng) for _ in range(n_styles))
    # Storeys per style: a style is "a kind of street", with a typical height.
    typical_floors = rng.integers(2, 7, size=n_styles)
    half = street_m / 2
    buildings: list[Building] = []
    side = 0
    for bj in range(-1, ny):
        for bi in range(-1, nx):
            x0, x1 = bi * block_m + half, (bi + 1) * block_m - half
            y0, y1 = bj * block_m + half, (bj + 1) * block_m - half
            # Corners counter-clockwise: walking from corner a to corner b the block is on the
            # left and the street on the right, so a viewer in the street facing the side has a
            # on the left: walls run a -> b (front normal = direction rotated clockwise).
            corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
            for k in range(4):
                a, b = np.array(corners[k]), np.array(corners[(k + 1) % 4])
                style = int(rng.integers(n_styles))
                buildings.extend(_split_side(a, b, style, side, int(typical_floors[style]), rng))
                side += 1
    margin = 1.6 * block_m
    extent = (-margin, -margin, (nx - 1) * block_m + margin, (ny - 1) * block_m + margin)
    xmin, ymin, xmax, ymax = extent
    # The skyline walls face inwards, so the viewer is on the other side than for a block
    # side: with the same counter-clockwise corners, they run b -> a.
    ring = [(xmin, ymin), (xmax, ymin), (xmax, ymax), (xmin, ymax)]
    for k in range(4):
        buildings.append(Building(ring[(k + 1) % 4], ring[k], 45.0, -1, -1))
    return CityLayout(nx, ny, block_m, street_m, styles, tuple(buildings), extent)


def _split_side(
    start: np.ndarray, end: np.ndarray, style: int, side: int, floors: int, rng: np.random.Generator
) -> list[Building]:
    """Split one block side into building fronts of 8-20 m with varying heights."""
    length = float(np.hypot(*(end - start)))
    cuts = [0.0]
    while length - cuts[-1] > 20.0:
        cuts.append(cuts[-1] + float(rng.uniform(8.0, 20.0)))
    if length - cuts[-1] < 8.0 and len(cuts) > 1:
        cuts.pop()  # merge a short remainder into the previous building
    cuts.append(length)
    direction = (end - start) / length
    out = []
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        storeys = max(1, floors + int(rng.integers(-1, 2)))
        height = storeys * 3.4 + float(rng.uniform(0.8, 2.5))
        p0, p1 = start + a * direction, start + b * direction
        out.append(
            Building(
                (float(p0[0]), float(p0[1])), (float(p1[0]), float(p1[1])), height, style, side
            )
        )
    return out
