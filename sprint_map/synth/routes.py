"""Routes through the street grid and the camera trajectory along them.

A route is a walk on the intersection graph without U-turns. Walks prefer streets (in the same
direction) that earlier traversals drove, with weight ``revisit`` against 1 for any other
street, so traversals overlap but also explore streets never driven before (and streets driven
the other way, which look different). Other weights for never-driven and reverse streets steer
walks towards novelty; :func:`overlap` measures, per frame, what earlier drives saw.

Driving a route: corners are rounded with a turning arc, the car keeps to the right lane, and its
speed (metres per frame) follows a smooth random profile, slows down in turns and sometimes
stops before an intersection for a few frames (repeated, almost identical frames, which the HMM's
"stay" transition must absorb).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from sprint_map.synth.layout import CityLayout, Node
from sprint_map.util.arrays import Float64Array

__all__ = ["Drive", "Edge", "Trajectory", "drive", "overlap", "plan_route"]

Edge = tuple[Node, Node]


def plan_route(
    layout: CityLayout,
    length_m: float,
    driven: set[Edge],
    rng: np.random.Generator,
    revisit: float = 3.0,
    new_weight: float = 1.0,
    reverse_weight: float = 1.0,
) -> list[Node]:
    """A walk of at least ``length_m`` metres.

    Parameters
    ----------
    layout : CityLayout
    length_m : float
        Minimum route length.
    driven : set of (node, node)
        Directed streets driven by earlier traversals; the walk starts on one of them when
        there are any, and prefers them.
    rng : numpy.random.Generator
    revisit : float
        Weight of a street already driven in the same direction.
    new_weight, reverse_weight : float
        Weights of a street never driven, and of one driven only the other way. With the
        defaults (1, 1) the walk is the plain ``revisit``-preferring one.
    """
    if driven:
        start, second = sorted(driven)[int(rng.integers(len(driven)))]
        route = [start, second]
    else:
        nodes = layout.nodes
        route = [nodes[int(rng.integers(len(nodes)))]]
    while (len(route) - 1) * layout.block_m < length_m:
        here = route[-1]
        options = [n for n in layout.neighbours(here) if len(route) < 2 or n != route[-2]]
        weights = np.array([
            revisit if (here, n) in driven
            else reverse_weight if (n, here) in driven
            else new_weight
            for n in options
        ])
        route.append(options[int(rng.choice(len(options), p=weights / weights.sum()))])
    return route


def overlap(
    xy: np.ndarray,
    heading_deg: np.ndarray,
    earlier_xy: np.ndarray,
    earlier_heading_deg: np.ndarray,
    radius_m: float,
    heading_tol_deg: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Which frames of a trajectory earlier frames saw, and which they saw the other way.

    The position ground truth's rule (within ``radius_m`` and ``heading_tol_deg``), vectorised
    with one KD-tree over all earlier frames.

    Returns
    -------
    matched : ndarray of bool, (N,)
        Some earlier frame is the same place.
    opposite : ndarray of bool, (N,)
        Not matched, but some earlier frame within ``radius_m`` faced the other way (heading
        difference of at least 135 degrees): a known street driven in the other direction.
    """
    from scipy.spatial import cKDTree

    matched = np.zeros(len(xy), dtype=bool)
    opposite = np.zeros(len(xy), dtype=bool)
    if len(earlier_xy) == 0:
        return matched, opposite
    near = cKDTree(earlier_xy).query_ball_point(xy, radius_m)
    for k, found in enumerate(near):
        if found:
            diff = np.abs((earlier_heading_deg[found] - heading_deg[k]) % 360.0)
            diff = np.minimum(diff, 360.0 - diff)
            matched[k] = bool((diff <= heading_tol_deg).any())
            opposite[k] = not matched[k] and bool((diff >= 135.0).any())
    return matched, opposite


@dataclass(frozen=True)
class Drive:
    """How a traversal drives its route (randomised per traversal)."""

    speed_m: float = 2.0  # mean distance per frame
    speed_sd: float = 0.25  # log-normal spread of the speed profile
    lane_m: float = 2.0  # offset to the right of the street's centre line
    turn_radius_m: float = 6.0
    stop_prob: float = 0.25  # chance of stopping before each intersection
    stop_frames: tuple[int, int] = (3, 12)  # inclusive range of a stop's length


@dataclass(frozen=True)
class Trajectory:
    """Per-frame camera poses."""

    xy: Float64Array  # (N, 2) metres
    heading_deg: Float64Array  # (N,) direction of travel, degrees CCW from +x, in [0, 360)
    route: tuple[Node, ...]  # intersections actually reached or approached


def drive(
    layout: CityLayout,
    route: Sequence[Node],
    n_frames: int,
    rng: np.random.Generator,
    params: Drive = Drive(),
) -> Trajectory:
    """Drive ``route`` for ``n_frames`` frames.

    Raises
    ------
    ValueError
        If the route is too short for ``n_frames`` frames (plan it with a margin).
    """
    path, turns = _rounded_path(layout, route, params.turn_radius_m)
    path = _offset_right(path, params.lane_m)
    seg = np.hypot(*np.diff(path, axis=0).T)
    arc = np.concatenate([[0.0], np.cumsum(seg)])
    tangent = np.diff(path, axis=0)
    heading = np.unwrap(np.arctan2(tangent[:, 1], tangent[:, 0]))
    heading = np.concatenate([heading, heading[-1:]])

    # Where to stop: 9 m before some intersections (just before the zebra crossing).
    node_arc = np.interp(turns, np.arange(len(arc)), arc)
    low, high = params.stop_frames
    stops = [
        (float(a - 9.0), int(rng.integers(low, high + 1)))
        for a in node_arc[1:-1]
        if rng.random() < params.stop_prob
    ]

    s = 0.0
    log_speed = 0.0
    positions = np.empty(n_frames)
    k = 0
    pending = sorted(stops)
    while k < n_frames:
        positions[k] = s
        k += 1
        if pending and s >= pending[0][0]:
            for _ in range(min(pending.pop(0)[1], n_frames - k)):
                positions[k] = s
                k += 1
        # AR(1) log-speed: correlated over ~20 frames, so speed changes are gradual.
        log_speed = 0.95 * log_speed + rng.normal(0, params.speed_sd * np.sqrt(1 - 0.95**2))
        step = params.speed_m * float(np.clip(np.exp(log_speed), 0.4, 1.8))
        curvature = abs(np.interp(s + 4.0, arc, heading) - np.interp(s, arc, heading))
        step *= 1.0 - 0.5 * min(1.0, curvature / 0.6)  # slow down through turns
        s += step
        if s > arc[-1]:
            raise ValueError("route too short for the requested number of frames")
    xy = np.stack([np.interp(positions, arc, path[:, 0]), np.interp(positions, arc, path[:, 1])], 1)
    headings = np.degrees(np.interp(positions, arc, heading)) % 360.0
    reached = int(np.searchsorted(node_arc, positions[-1])) + 1
    return Trajectory(xy, headings, tuple(route[: min(len(route), reached + 1)]))


def _rounded_path(
    layout: CityLayout, route: Sequence[Node], radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Dense (0.25 m) centre-line polyline with rounded corners; also each node's index in it."""
    points = [layout.node_xy(n) for n in route]
    dense: list[np.ndarray] = [points[0][None, :]]
    node_index = [0.0]
    for i in range(1, len(points)):
        a, b = points[i - 1], points[i]
        c = points[i + 1] if i + 1 < len(points) else None
        d_in = (b - a) / np.linalg.norm(b - a)
        start = dense[-1][-1]
        if c is None or np.allclose(d_in, (c - b) / np.linalg.norm(c - b)):
            end = b
            corner = None
        else:
            d_out = (c - b) / np.linalg.norm(c - b)
            end = b - d_in * radius
            corner = (end, b, b + d_out * radius)
        n = max(2, int(np.ceil(np.linalg.norm(end - start) / 0.25)) + 1)
        dense.append(np.linspace(start, end, n)[1:])
        if corner is None:
            node_index.append(sum(len(p) for p in dense) - 1)
        else:
            p0, p1, p2 = corner  # quadratic Bezier through the corner
            t = np.linspace(0, 1, 12)[1:, None]
            arc_points = (1 - t) ** 2 * p0 + 2 * (1 - t) * t * p1 + t**2 * p2
            node_index.append(sum(len(p) for p in dense) - 1 + len(arc_points) / 2)
            dense.append(arc_points)
    return np.concatenate(dense), np.array(node_index)


def _offset_right(path: np.ndarray, offset: float) -> np.ndarray:
    """Shift a polyline ``offset`` metres to the right of its direction of travel."""
    tangent = np.gradient(path, axis=0)
    tangent /= np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-9)
    right = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)
    return path + offset * right
