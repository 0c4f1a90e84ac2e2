"""Geometry of the synthetic city: a grid of streets between square blocks of buildings.

Intersections sit at ``(i * block_m, j * block_m)`` for ``0 <= i < nx``, ``0 <= j < ny``; streets
of width ``street_m`` (sidewalks included) join neighbouring intersections. Each city block is a
solid square whose four sides are split into building fronts ("walls") of 8-20 m, and a ring of
blocks around the grid gives every street buildings on both sides. Four tall, distant walls with
a skyline close the world off, so every camera ray hits something.

Each block *side* gets one facade style from a small shared pool, so whole street sides resemble
other street sides elsewhere (perceptual aliasing); buildings within a side vary in height and
details. With ``alias_streets`` > 0 some whole streets are copies of other streets, as real
aliasing is: the same facade styles, palette and rhythm of buildings on both sides, in the same
order for the same direction of travel, but other buildings (heights, details, signs) and other
gaps between them; ``identical_twins`` of the copies are pixel-identical (only the cross
streets, the ground and the conditions tell them apart), listed in ``CityLayout.twins``.
Coordinates are metres, x east, y north; headings are degrees counter-clockwise from +x.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sprint_map.synth.textures import FacadeStyle, random_style

__all__ = ["Building", "CityLayout", "Node", "build_layout"]

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
    twin: int = -1  # index of the building whose texture this one reuses (identical twin)
    copy_of: int = -1  # index of the building this one copies (twin or lookalike street)

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
    #: Streets (as their two intersections) that are pixel-identical twins of another street,
    #: copies and originals alike.
    twins: tuple[tuple[Node, Node], ...] = ()

    def on_twin(self, xy: np.ndarray) -> np.ndarray:
        """Which positions ``(N, 2)`` lie on a twin street, between its two crossings. O(N)."""
        out = np.zeros(len(xy), dtype=bool)
        half = self.street_m / 2
        for a, b in self.twins:
            pa, pb = self.node_xy(a), self.node_xy(b)
            u = (pb - pa) / self.block_m
            rel = np.asarray(xy, dtype=np.float64) - pa
            along = rel @ u
            across = np.abs(rel @ np.array([-u[1], u[0]]))
            out |= (along > half) & (along < self.block_m - half) & (across < half)
        return out

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
    alias_streets: float = 0.0,
    identical_twins: int = 1,
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
    alias_streets : float
        Share of the streets (rounded down) made copies of another street, which keeps its own
        look; 0 draws no extra random numbers, so the city is the same as without the option.
    identical_twins : int
        How many of the copies are pixel-identical (the others are lookalikes: same styles
        and rhythm, other buildings, signs and gaps); listed in :attr:`CityLayout.twins`.
    """
    if nx < 2 or ny < 2:
        raise ValueError("the grid needs at least 2 x 2 intersections")
    if not 0 < street_m < block_m / 2:
        raise ValueError("street_m must be positive and less than half of block_m")
    if n_styles < 1:
        raise ValueError("n_styles must be >= 1")
    if not 0 <= alias_streets <= 0.5:
        raise ValueError("alias_streets must be in [0, 0.5]")
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
    twins: tuple[tuple[Node, Node], ...] = ()
    if alias_streets > 0:
        buildings, twins = _alias_streets(buildings, nx, ny, alias_streets, identical_twins, rng)
    margin = 1.6 * block_m
    extent = (-margin, -margin, (nx - 1) * block_m + margin, (ny - 1) * block_m + margin)
    xmin, ymin, xmax, ymax = extent
    # The skyline walls face inwards, so the viewer is on the other side than for a block
    # side: with the same counter-clockwise corners, they run b -> a.
    ring = [(xmin, ymin), (xmax, ymin), (xmax, ymax), (xmin, ymax)]
    for k in range(4):
        buildings.append(Building(ring[(k + 1) % 4], ring[k], 45.0, -1, -1))
    return CityLayout(nx, ny, block_m, street_m, styles, tuple(buildings), extent, twins)


def _street_sides(nx: int, ny: int) -> list[tuple[int, int]]:
    """Per street, the block sides on its right and on its left, driving east or north.

    Streets in :meth:`CityLayout.nodes` order, each node's east street before its north street.
    Side indices follow :func:`build_layout`: blocks row by row from ``(-1, -1)``, four sides
    each (south, east, north, west faces of the block, counter-clockwise). Both sides run the
    same way for the same direction of travel (the right one towards the car, the left one
    away), so a side copied onto another street's side looks the same from the car.
    """

    def side(bi: int, bj: int, k: int) -> int:
        return ((bj + 1) * (nx + 1) + bi + 1) * 4 + k

    streets = []
    for j in range(ny):
        for i in range(nx):
            if i + 1 < nx:  # east: the block below shows its north face, the one above its south
                streets.append((side(i, j - 1, 2), side(i, j, 0)))
            if j + 1 < ny:  # north: the block right shows its west face, the one left its east
                streets.append((side(i, j, 3), side(i - 1, j, 1)))
    return streets


def _street_nodes(nx: int, ny: int) -> list[tuple[Node, Node]]:
    """The intersections each street of :func:`_street_sides` joins, in the same order."""
    out = []
    for j in range(ny):
        for i in range(nx):
            if i + 1 < nx:
                out.append(((i, j), (i + 1, j)))
            if j + 1 < ny:
                out.append(((i, j), (i, j + 1)))
    return out


def _alias_streets(
    buildings: list[Building], nx: int, ny: int, share: float, identical: int,
    rng: np.random.Generator,
) -> tuple[list[Building], tuple[tuple[Node, Node], ...]]:
    """Make ``share`` of the streets copies of other (original) streets.

    The first ``identical`` copies are pixel-identical twins (every building samples its
    original's texture); the others are lookalikes, as real aliasing is: each building keeps
    its original's style (palette, windows, shop fronts) and place in the rhythm of the
    street, but its ends move by up to 1.5 m (other gaps), its height by up to 1.7 m, and it is
    drawn anew (other details, signs, posters). Returns the buildings and the twin streets
    (copies and their originals, as pairs of intersections).
    """
    streets = _street_sides(nx, ny)
    nodes = _street_nodes(nx, ny)
    order = [int(k) for k in rng.permutation(len(streets))]
    n_copies = int(share * len(streets))
    copies, originals = order[:n_copies], order[n_copies:]
    by_side: dict[int, list[Building]] = {}
    for building in buildings:
        by_side.setdefault(building.side, []).append(building)
    source_of: dict[int, int] = {}  # copied side -> original side
    identical_sides: set[int] = set()
    twins: list[tuple[Node, Node]] = []
    for k, street in enumerate(copies):
        original = originals[int(rng.integers(len(originals)))]
        for target, source in zip(streets[street], streets[original], strict=True):
            source_of[target] = source
            if k < identical:
                identical_sides.add(target)
        if k < identical:
            twins.extend([nodes[street], nodes[original]])
    out: list[Building] = []
    first: dict[int, int] = {}  # side -> index in ``out`` of its first building
    for side in sorted(by_side, key=lambda s: (s in source_of, s)):  # originals first
        if side not in source_of:
            first[side] = len(out)
            out.extend(by_side[side])
            continue
        walls = by_side[side]
        start, end = np.array(walls[0].p0), np.array(walls[-1].p1)
        length = float(np.hypot(*(end - start)))
        direction = (end - start) / length
        model = by_side[source_of[side]]
        origin = np.array(model[0].p0)
        cuts = [float(np.hypot(*(np.array(b.p1) - origin))) for b in model[:-1]]
        heights = [b.height_m for b in model]
        twin = side in identical_sides
        if not twin:  # same rhythm, other gaps and heights
            cuts = [c + float(rng.uniform(-1.5, 1.5)) for c in cuts]
            heights = [max(3.5, h + float(rng.uniform(-1.7, 1.7))) for h in heights]
        ends = [0.0, *cuts, length]
        for k, b in enumerate(model):
            p0, p1 = start + ends[k] * direction, start + ends[k + 1] * direction
            out.append(Building((float(p0[0]), float(p0[1])), (float(p1[0]), float(p1[1])),
                                heights[k], b.style, side,
                                first[source_of[side]] + k if twin else -1,
                                first[source_of[side]] + k))
    return out, tuple(twins)


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
