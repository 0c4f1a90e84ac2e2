"""Building blocks of the synthetic city: layout, routes, renderer, conditions."""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.synth.atlas import build_atlas
from sprint_map.synth.conditions import CONDITIONS, Appearance
from sprint_map.synth.layout import build_layout
from sprint_map.synth.render import Camera, Renderer
from sprint_map.synth.routes import Drive, drive, plan_route


@pytest.fixture(scope="module")
def world():
    rng = np.random.default_rng(11)
    layout = build_layout(rng, nx=3, ny=3, block_m=60.0, street_m=14.0, n_styles=3)
    return layout, Renderer(layout, build_atlas(layout, rng), Camera())


def test_layout_buildings_face_the_streets(world):
    layout, _ = world
    assert len(layout.styles) == 3
    walls = [b for b in layout.buildings if b.style >= 0]
    assert all(8.0 - 1e-9 <= b.length_m <= 28.0 for b in walls)
    # Each front's normal (direction rotated clockwise) points into a street: the point 1 m in
    # front of the middle of the wall lies outside every block.
    half = layout.street_m / 2
    for b in walls:
        p0, p1 = np.array(b.p0), np.array(b.p1)
        edge = p1 - p0
        normal = np.array([edge[1], -edge[0]]) / np.linalg.norm(edge)
        x, y = (p0 + p1) / 2 + normal
        in_x = ((x + half) % layout.block_m) > layout.street_m
        in_y = ((y + half) % layout.block_m) > layout.street_m
        assert not (in_x and in_y), b


def test_routes_follow_streets_without_u_turns(world):
    layout, _ = world
    rng = np.random.default_rng(0)
    route = plan_route(layout, 1000.0, set(), rng)
    assert (len(route) - 1) * layout.block_m >= 1000.0
    for a, b in zip(route[:-1], route[1:], strict=True):
        assert b in layout.neighbours(a)
    for a, c in zip(route[:-2], route[2:], strict=True):
        assert a != c


def test_routes_prefer_driven_streets(world):
    layout, _ = world
    rng = np.random.default_rng(1)
    first = plan_route(layout, 600.0, set(), rng)
    driven = set(zip(first[:-1], first[1:], strict=True))
    shares = []
    for revisit in (1.0, 20.0):
        later = [plan_route(layout, 600.0, driven, rng, revisit) for _ in range(20)]
        steps = [(a, b) for r in later for a, b in zip(r[:-1], r[1:], strict=True)]
        shares.append(np.mean([s in driven for s in steps]))
    assert shares[1] > shares[0] + 0.2


def test_drive_speed_stops_heading_and_lane(world):
    layout, _ = world
    rng = np.random.default_rng(2)
    route = plan_route(layout, 2000.0, set(), rng)
    params = Drive(speed_m=2.0, stop_prob=1.0, lane_m=2.0)
    traj = drive(layout, route, 400, rng, params)
    assert traj.xy.shape == (400, 2) and traj.heading_deg.shape == (400,)
    steps = np.hypot(*np.diff(traj.xy, axis=0).T)
    assert steps.max() <= 1.8 * 2.0 + 0.2
    assert (steps < 1e-9).sum() >= 3  # stopped at least once (stop_prob=1)
    moving = steps > 0.5
    direction = np.degrees(np.arctan2(*np.diff(traj.xy, axis=0)[:, ::-1].T))
    diff = (direction - traj.heading_deg[:-1] + 180) % 360 - 180
    assert np.abs(diff[moving]).max() < 30  # heading = direction of travel
    # The car stays on the road: within the street half-width of a street centre line.
    half = layout.street_m / 2
    off_x = np.abs((traj.xy[:, 0] + 30) % 60 - 30)
    off_y = np.abs((traj.xy[:, 1] + 30) % 60 - 30)
    assert (np.minimum(off_x, off_y) <= half).all()
    assert traj.route[0] == route[0] and len(traj.route) <= len(route)


def test_drive_refuses_a_short_route(world):
    layout, _ = world
    with pytest.raises(ValueError, match="too short"):
        drive(layout, [(0, 0), (1, 0)], 500, np.random.default_rng(0))


def test_render_geometry(world):
    layout, renderer = world
    # At (30, 0) facing north, the block south-west corner at y = street_m / 2 = 7 m ahead.
    view = renderer.render(30.0, 0.0, 90.0, height_m=1.6)
    assert view.image.shape == (120, 160, 3) and view.image.dtype == np.uint8
    assert view.depth[60, 78:82].mean() == pytest.approx(7.0, abs=0.3)
    # The wall's foot is 1.6 m below the camera at 7 m: f * 1.6 / 7 = 18.3 rows below the
    # horizon (f = 80 px for 160 px and 90 degrees); below it is road, above it wall or sky.
    centre = view.ground[:, 78:82].mean(axis=1)
    assert (centre[:77] == 0).all() and (centre[80:] == 1).all()
    assert (view.sky[60:] == 0).all() and (view.ground[:60] == 0).all()
    # Looking down a long street, the sky is visible above the far end.
    along = renderer.render(0.0, 0.0, 0.0)
    assert along.sky[:10, 70:90].mean() > 0.5
    # Same pose, same image; a step forward changes it.
    np.testing.assert_array_equal(renderer.render(30.0, 0.0, 90.0).image, view.image)
    assert not np.array_equal(renderer.render(30.0, 1.0, 90.0).image, view.image)


def test_render_outside_the_city_is_an_error(world):
    _, renderer = world
    with pytest.raises(ValueError, match="outside"):
        renderer.render(10_000.0, 0.0, 0.0)


@pytest.mark.parametrize("name", sorted(set(CONDITIONS) - {"day"}))
def test_conditions_change_the_image_deterministically(world, name):
    _, renderer = world
    view = renderer.render(0.0, 0.0, 0.0, sky=CONDITIONS[name].sky)
    day = Appearance(CONDITIONS["day"], np.random.default_rng(0)).apply(view, 0.0)
    condition = CONDITIONS[name].jittered(np.random.default_rng(4))
    a = Appearance(condition, np.random.default_rng(9)).apply(view, 0.0)
    b = Appearance(condition, np.random.default_rng(9)).apply(view, 0.0)
    np.testing.assert_array_equal(a, b)
    assert a.shape == day.shape and a.dtype == np.uint8
    assert np.abs(a.astype(int) - day.astype(int)).mean() > 5


def test_fog_hides_distant_things(world):
    _, renderer = world
    view = renderer.render(0.0, 0.0, 0.0)
    fog = Appearance(CONDITIONS["fog"], np.random.default_rng(0)).apply(view, 0.0)
    far = view.depth > 150
    near = view.depth < 15
    grey = np.array(CONDITIONS["fog"].fog)
    # Distance to the fog colour, far vs near pixels.
    distance = np.abs(fog.astype(float) - grey).mean(axis=2)
    assert distance[far].mean() < distance[near].mean()
