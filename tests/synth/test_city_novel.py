"""The harder generated world (``city-novel``): novel streets, other-direction stretches, aliased
streets; and the streamed renderer."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from sprint_map.frontend import GroundTruth
from sprint_map.frontend.groundtruth import GroundTruthSpec
from sprint_map.synth import PRESETS, CityConfig, iter_city, render_city
from sprint_map.synth.atlas import build_atlas
from sprint_map.synth.layout import CityLayout, build_layout
from sprint_map.synth.render import Camera, Renderer

# Routes do not depend on the image size: tiny images keep the test about the ground truth.
NOVEL = dataclasses.replace(PRESETS["city-novel"], width=40, height=30)


@pytest.fixture(scope="module", params=[0, 1])
def novel_city(request):
    return render_city(n_traversals=6, frames_per_traversal=300, seed=request.param,
                       config=NOVEL)


def shares(city) -> list[tuple[float, float, float]]:
    """Per traversal after the first, from the ground truth: the share of frames with no true
    match among earlier traversals, the share seen by an earlier one facing the other way
    (a heading 180 degrees off within tolerance), and the share with a true match."""
    gt = city.ground_truth()
    spec = city.config.ground_truth_spec()
    positions = dict(zip(city.names, (t.positions for t in city.traversals), strict=True))
    reverse = {f"{n}-reversed": p.copy() for n, p in positions.items()}
    for p in reverse.values():
        p[:, 3] = (p[:, 3] + 180.0) % 360.0
    reverse_gt = GroundTruth(spec, positions={**positions, **reverse})
    out = []
    for i in range(1, len(city.names)):
        name, earlier = city.names[i], city.names[:i]
        frames = np.arange(len(city.traversals[i].positions))
        matched = gt.has_match(name, frames, earlier)
        other_way = reverse_gt.has_match(f"{name}-reversed", frames, earlier) & ~matched
        out.append((float(1 - matched.mean()), float(other_way.mean()), float(matched.mean())))
    return out


def test_later_traversals_are_mostly_novel_with_other_direction_stretches(novel_city):
    found = shares(novel_city)
    print("novel / other way / matched per traversal:", [tuple(round(v, 2) for v in s)
                                                         for s in found])
    for novel, other_way, matched in found:
        assert novel >= 0.5  # at least half the frames have no true match in the map
        assert other_way >= 0.05  # some known streets driven the other way
        assert matched >= 0.15  # and still known ground to localise on


def test_plain_city_routes_are_not_novelty_driven():
    """The default city prefers driven streets: the novelty search is what makes city-novel
    novel (some traversal of the plain city is mostly on known ground)."""
    plain = render_city(6, 300, seed=0, config=dataclasses.replace(CityConfig(), width=40,
                                                                   height=30))
    assert min(novel for novel, _, _ in shares(plain)) < 0.5


def test_novel_routes_are_deterministic():
    a = render_city(3, 60, seed=4, config=NOVEL, workers=1)
    b = render_city(3, 60, seed=4, config=NOVEL, workers=2)
    for ta, tb in zip(a.traversals, b.traversals, strict=True):
        np.testing.assert_array_equal(ta.positions, tb.positions)
        np.testing.assert_array_equal(ta.images, tb.images)
    c = render_city(3, 60, seed=5, config=NOVEL)
    assert not np.array_equal(c.traversals[1].positions, a.traversals[1].positions)


def test_iter_city_streams_what_render_city_renders():
    config = CityConfig(grid=(2, 3), width=40, height=30)
    whole = render_city(4, 20, seed=2, config=config)
    streamed = list(iter_city(4, 20, seed=2, config=config, workers=2))
    assert [t.name for t in streamed] == whole.names
    for ta, tb in zip(streamed, whole.traversals, strict=True):
        np.testing.assert_array_equal(ta.images, tb.images)
        np.testing.assert_array_equal(ta.positions, tb.positions)


def _view_of_wall(layout: CityLayout, renderer: Renderer, index: int) -> np.ndarray:
    """The view from the right lane, 12 m before the middle of wall ``index`` (on the right)."""
    b = layout.buildings[index]
    p0, p1 = np.array(b.p0), np.array(b.p1)
    along = (p0 - p1) / np.linalg.norm(p0 - p1)  # driving with the wall on the right
    normal = np.array([-along[1], along[0]])  # from the wall into the street
    at = (p0 + p1) / 2 + normal * (layout.street_m / 2 - 2.0) - along * 12.0
    heading = float(np.degrees(np.arctan2(along[1], along[0])))
    return renderer.render(float(at[0]), float(at[1]), heading).image.astype(np.float64)


@pytest.fixture(scope="module")
def aliased():
    rng = np.random.default_rng(3)
    layout = build_layout(rng, nx=4, ny=4, n_styles=3, alias_streets=0.25)
    return layout, build_atlas(layout, rng)


def test_aliased_streets_are_copies(aliased):
    layout, atlas = aliased
    copies = [i for i, b in enumerate(layout.buildings) if b.copy_of >= 0]
    copied_sides = {layout.buildings[i].side for i in copies}
    # A quarter of the 24 streets, both sides each.
    assert len(copied_sides) == 2 * int(0.25 * 24)
    for i in copies:
        b, model = layout.buildings[i], layout.buildings[layout.buildings[i].copy_of]
        assert model.copy_of < 0 and model.side not in copied_sides and model.side != b.side
        # Same style and rhythm of buildings; the ends move by at most 1.5 m each.
        assert b.style == model.style
        assert abs(b.length_m - model.length_m) <= 3.0 + 1e-9
        assert abs(b.height_m - model.height_m) <= 1.7 + 1e-9


def test_one_copied_street_is_an_identical_twin_the_others_lookalikes(aliased):
    layout, atlas = aliased
    twins = [i for i, b in enumerate(layout.buildings) if b.twin >= 0]
    lookalikes = [i for i, b in enumerate(layout.buildings) if b.copy_of >= 0 and b.twin < 0]
    assert {layout.buildings[i].side for i in twins} and lookalikes
    assert len({layout.buildings[i].side for i in twins}) == 2  # one street, both sides
    assert len(layout.twins) == 2  # the copy and its original, as pairs of intersections
    for i in twins:
        b, twin = layout.buildings[i], layout.buildings[layout.buildings[i].twin]
        assert b.twin == b.copy_of and (b.height_m, b.style) == (twin.height_m, twin.style)
        assert b.length_m == pytest.approx(twin.length_m)
        np.testing.assert_array_equal(atlas.rects[i], atlas.rects[b.twin])
    # Both twin streets' middles are on a twin street; the middle of a lookalike's is not.
    for a, b in layout.twins:
        middle = (layout.node_xy(a) + layout.node_xy(b)) / 2
        assert layout.on_twin(middle[None])[0]
    wall = layout.buildings[lookalikes[0]]
    assert not layout.on_twin(((np.array(wall.p0) + np.array(wall.p1)) / 2)[None])[0]
    # From the car: a twin's wall is the original's, pixel for pixel; a lookalike's resembles
    # its original's (same style, other details and signs) more than a stranger's, but is not it.
    renderer = Renderer(layout, atlas, Camera())
    originals = [i for i, b in enumerate(layout.buildings) if b.copy_of < 0 and b.style >= 0]
    right = np.s_[:50, 110:]  # the near right wall, above the ground
    for i in twins[::3]:
        view = _view_of_wall(layout, renderer, i)
        model = _view_of_wall(layout, renderer, layout.buildings[i].twin)
        assert np.abs(view[right] - model[right]).mean() < 1.0
    same, other = [], []
    for k, i in enumerate(lookalikes[::3]):
        view = _view_of_wall(layout, renderer, i)
        model = _view_of_wall(layout, renderer, layout.buildings[i].copy_of)
        stranger = _view_of_wall(layout, renderer, originals[(7 * k) % len(originals)])
        same.append(np.abs(view[right] - model[right]).mean())
        other.append(np.abs(view[right] - stranger[right]).mean())
    print("lookalike vs original, vs a stranger:", np.median(same), np.median(other))
    assert min(same) > 3.0  # never pixel-identical
    assert np.median(same) < 0.8 * np.median(other)


def test_no_identical_twins_when_asked(aliased):
    layout = build_layout(np.random.default_rng(3), nx=4, ny=4, n_styles=3,
                          alias_streets=0.25, identical_twins=0)
    assert layout.twins == () and all(b.twin < 0 for b in layout.buildings)
    assert sum(b.copy_of >= 0 for b in layout.buildings) > 0


def test_alias_zero_draws_nothing_extra():
    a = build_layout(np.random.default_rng(9), 3, 3, alias_streets=0.0)
    b = build_layout(np.random.default_rng(9), 3, 3)
    assert a == b and all(x.twin < 0 for x in a.buildings)


@pytest.mark.parametrize("changes", [
    {"alias_streets": 0.6}, {"alias_streets": -0.1}, {"novel_fraction": 0.9},
    {"novel_fraction": 0.3, "reverse_fraction": 0.4}, {"reverse_fraction": 0.1},
])
def test_invalid_novelty_config(changes):
    with pytest.raises(ValueError):
        CityConfig(**changes)


def test_presets():
    assert PRESETS["city"] == CityConfig()
    novel = PRESETS["city-novel"]
    assert novel.novel_fraction >= 0.5 and novel.reverse_fraction > 0 and novel.alias_streets > 0
    assert CityConfig.from_dict(novel.to_dict()) == novel
    assert GroundTruthSpec.from_dict(novel.ground_truth_spec().to_dict()).heading_deg == 45.0
