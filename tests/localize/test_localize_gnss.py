"""GNSS as an optional cue (sprint_map/localize/gnss.py): fixes against the map's positions.

Every fix here comes from the simulated receiver (drift, dropouts, multipath jumps), never
from ground truth plus white noise.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sprint_map import MapConfig
from sprint_map.errors import InputError
from sprint_map.frontend.gnss import GnssModel, simulate_fixes
from sprint_map.localize.gnss import (
    GnssAid,
    GnssConfig,
    PositionIndex,
    consistent,
    validate_fixes,
)
from sprint_map.map import SprintMap

DIM = 32
LENGTH = 150
SPACING_M = 5.0


def street(rng: np.random.Generator, length: int = LENGTH) -> np.ndarray:
    """Places along a street: neighbouring places alike (a random walk of appearance)."""
    steps = rng.normal(size=(length, DIM)).astype(np.float32)
    return np.cumsum(steps, axis=0) / 3.0


def driven(places: np.ndarray, rng: np.random.Generator, noise: float = 1.0) -> np.ndarray:
    return (places + rng.normal(0, noise, places.shape)).astype(np.float32)


def along(y: float, length: int = LENGTH, start: int = 0) -> np.ndarray:
    """Ground truth of a drive along the street at ``y`` from place ``start``."""
    return np.c_[(start + np.arange(length)) * SPACING_M, np.full(length, y)]


def receiver(seed: int, sigma: float = 10.0) -> tuple[GnssModel, int]:
    # more dropouts and jumps than the default, so that every short test drive has some
    return GnssModel(sigma=sigma, dropout_rate=1 / 60, dropout_frames=(5, 12),
                     jump_rate=1 / 40, jump_frames=(1, 4)), seed


def fixes_for(truth: np.ndarray, seed: int, sigma: float = 10.0) -> np.ndarray:
    model, s = receiver(seed, sigma)
    return simulate_fixes(truth, model, s)


@pytest.fixture
def twins(tmp_path):
    """A map of a street and its identical twin 400 m away (pixel-identical: no image
    method can tell them), each mapped with simulated fixes; and a drive along the first."""
    rng = np.random.default_rng(3)
    places = street(rng)
    path = tmp_path / "twins.map"
    with SprintMap.create(path, MapConfig(dim=DIM)) as m:
        for i, y in enumerate((0.0, 400.0)):
            truth = along(y)
            m.add_sequence(driven(places, rng, 0.3), name=f"street-{i}",
                           positions=fixes_for(truth, 10 + i)[:, :2])
    query = driven(places[20:140], rng)
    return path, query, along(0.0, 120, start=20)


# --- fixes, config, index -------------------------------------------------------------------
@pytest.mark.parametrize(("fixes", "n", "message"), [
    (np.zeros((4, 2)), 5, "4 rows"),
    (np.zeros((6, 3)) + [0, 0, 1], 5, "6 rows"),
    (np.zeros((5, 4)), 5, "expected one row x, y"),
    (np.array([[0, np.nan]] * 5), 5, "frame 0: x, y .* out of range"),
    (np.array([[0, np.inf]] * 5), 5, "out of range"),
    (np.array([[2e8, 0]] * 5), 5, "out of range"),
    (np.array([[0, 0, 0.0]] * 5), 5, "frame 0: sigma_m 0 must be a finite number > 0"),
    (np.array([[0, 0, -3]] * 5), 5, "sigma_m -3"),
    (np.array([[0, 0, np.inf]] * 5), 5, "sigma_m inf"),
])
def test_bad_fixes_are_one_clear_error(fixes, n, message):
    with pytest.raises(InputError, match=f"GNSS fixes: .*{message}"):
        validate_fixes(fixes, n, 10.0)


def test_fixes_take_the_default_sigma_and_keep_frames_without_a_fix():
    out = validate_fixes([[1, 2, np.nan], [np.nan, np.nan, np.nan], [3, 4, 2.5]], 3, 7.0)
    np.testing.assert_array_equal(out[[0, 2]], [[1, 2, 7.0], [3, 4, 2.5]])
    assert np.isnan(out[1]).all()


@pytest.mark.parametrize("field", ["sigma_m", "map_sigma_m", "gate_m", "n_sigma",
                                   "far_log_cap"])
@pytest.mark.parametrize("value", [0.0, -1.0, math.nan, math.inf])
def test_config_refuses_bad_values(field, value):
    with pytest.raises(ValueError, match=field):
        GnssConfig(**{field: value})


def test_gate_and_weight():
    cfg = GnssConfig(gate_m=25.0, n_sigma=3.0)
    assert cfg.gate(3.0, 4.0) == 25.0  # 3 * 5 m < 25 m
    assert cfg.gate(30.0, 40.0) == pytest.approx(150.0)
    sigma = math.hypot(10, 10)
    assert cfg.weight(cfg.gate(10, 10), 10, 10) == 1.0  # inside the gate: no opinion
    assert cfg.weight(cfg.gate(10, 10) + sigma, 10, 10) == pytest.approx(math.exp(-0.5))
    assert cfg.weight(1e6, 10, 10) == pytest.approx(math.exp(-cfg.far_log_cap))


def test_map_config_stored_without_gnss_opens_with_the_defaults():
    stored = MapConfig(dim=8).to_dict()
    assert stored["gnss"] == {"sigma_m": 10.0, "map_sigma_m": 10.0, "gate_m": 25.0,
                              "n_sigma": 3.0, "max_added": 4, "far_log_cap": 8.0,
                              "added_log_weight": -1.0, "consistency_window": 8,
                              "heading_gate_deg": 45.0, "offset_m": 20.0}
    del stored["gnss"]  # a map written before GNSS
    assert MapConfig.from_dict(stored).gnss == GnssConfig()


def test_position_index_by_vertex_and_nearest():
    rows = np.c_[np.arange(10) * 5.0, np.zeros(10)]
    rows[3] = np.nan  # a frame without a fix, between two with one
    rows[9] = np.nan  # the last frame without a fix
    with_sigma = np.c_[np.arange(5) * 5.0, np.full(5, 100.0), np.full((5, 2), np.nan),
                       np.full(5, 2.0)]
    index = PositionIndex(20, [(0, rows), (12, with_sigma)], map_sigma=9.0)
    assert index.size == 14
    xy, sigma, heading = index.position(np.array([0, 3, 9, 11, 13, 99, -1]))
    np.testing.assert_allclose(heading[[0, 1]], 0.0)  # east along the track
    assert np.isnan(heading[[3, 5, 6]]).all()
    np.testing.assert_array_equal(xy[:2], [[0, 0], [15, 0]])  # bridged on the line
    assert np.isnan(xy[[2, 3, 5, 6]]).all()  # no fix after it, no position, beyond the map
    np.testing.assert_array_equal(sigma[[0, 1, 4]], [9.0, 9.0 + 0.25 * 10, 2.0])
    ids, metres, seq = index.near(6.0, 99.0, k=3)
    assert ids[0] == 13 and metres[0] == pytest.approx(math.hypot(1, 1)) and seq[0] == 1


def test_cue_adds_mapped_vertices_near_the_fix_and_weighs_far_hits():
    rows = np.c_[np.arange(100) * 5.0, np.zeros(100)]
    twin = np.c_[np.arange(100) * 5.0, np.full(100, 500.0)]
    index = PositionIndex(200, [(0, rows), (100, twin)], map_sigma=10.0)
    fixes = validate_fixes([[250.0, 3.0], [np.nan, np.nan]], 2, 10.0)
    aid = GnssAid(GnssConfig(), index, fixes)
    # retrieval found only the twin (vertices 150..152, 500 m away): the street is added
    ids, dists, weights, sink_weight = aid.cue(0, np.array([150, 151, 152]),
                                               np.array([1.0, 1.5, 2.0]))
    assert ids[:3].tolist() == [150, 151, 152] and 50 in ids.tolist()
    assert dists[3:].tolist() == [2.0] * (len(ids) - 3)  # the farthest hit's distance
    np.testing.assert_allclose(weights[:3], math.exp(-8.0))  # capped
    np.testing.assert_allclose(weights[3:], math.exp(-1.0))  # added: restart mass, no evidence
    assert sink_weight == 1.0  # a mapped place is near the fix
    assert aid.cue(1, np.array([150]), np.array([1.0])) is None  # no fix: nothing changes
    assert aid.distance(0, 50) == (pytest.approx(3.0), True)
    d, plausible = aid.distance(0, 150)
    assert d == pytest.approx(math.hypot(0, 497)) and not plausible
    assert math.isnan(aid.distance(1, 50)[0])


def test_fixes_off_the_drives_track_are_dropped():
    """Multipath jumps (30-80 m for a few frames) leave the drive's track: dropped, as frames
    without a fix; the drift (time-correlated, 10 m) stays."""
    truth = along(0.0, 3000)
    jumpy = simulate_fixes(truth, GnssModel(sigma=10.0), 4)
    drift = simulate_fixes(truth, GnssModel(sigma=10.0, jump_rate=0.0), 4)
    jumped = np.hypot(*(jumpy[:, :2] - drift[:, :2]).T) > 0
    kept = consistent(validate_fixes(jumpy, None, 10.0), GnssConfig())
    assert jumped.sum() > 20 and (kept & jumped).sum() <= 0.1 * jumped.sum()
    assert (~kept & ~jumped & ~np.isnan(jumpy[:, 0])).mean() < 0.01
    assert not kept[np.isnan(jumpy[:, 0])].any()
    everything = consistent(jumpy, GnssConfig(consistency_window=0))
    np.testing.assert_array_equal(everything, ~np.isnan(jumpy[:, 0]))


def test_a_place_against_the_direction_of_travel_is_not_plausible():
    """The same street driven the other way: as near as can be, but facing the other way."""
    rows = np.c_[np.arange(100) * 5.0, np.zeros(100)]
    index = PositionIndex(100, [(0, rows)], map_sigma=10.0)
    east = np.c_[np.arange(40, 60) * 5.0, np.full(20, 2.0)]
    for track, expected in ((east, True), (east[::-1], False)):
        aid = GnssAid(GnssConfig(), index, validate_fixes(track, None, 10.0))
        assert aid.distance(10, 50)[1] is expected
        cue = aid.cue(10, np.array([50]), np.array([1.0]))
        assert cue is not None and bool(cue[2][0] == 1.0) is expected
        added = cue[0][1:]
        assert added.size == (4 if expected else 0)  # nothing added against the direction
    aid = GnssAid(GnssConfig(heading_gate_deg=180.0), index,
                  validate_fixes(east[::-1], None, 10.0))
    assert aid.distance(10, 50)[1]


def test_a_place_stuck_while_the_fixes_move_on_is_off_track():
    rows = np.c_[np.arange(100) * 5.0, np.zeros(100)]
    index = PositionIndex(100, [(0, rows)], map_sigma=10.0)
    truth = np.c_[np.arange(30, 60) * 5.0, np.zeros(30)]
    aid = GnssAid(GnssConfig(), index, validate_fixes(truth + [4.0, 3.0], None, 10.0))
    frames = np.arange(30)
    places = 30 + frames.copy()
    places[10:20] = 40  # stuck on one image for ten frames (50 m)
    off = aid.off_track(frames, places)
    assert not off[:14].any() and off[16:20].all() and not off[21:].any()
    assert not GnssAid(GnssConfig(offset_m=0.0), index, aid.fixes).off_track(frames,
                                                                             places).any()


def test_cue_far_from_every_mapped_place_raises_the_unmapped_place():
    rows = np.c_[np.arange(100) * 5.0, np.zeros(100)]
    index = PositionIndex(100, [(0, rows)], map_sigma=10.0)
    fixes = validate_fixes([[250.0, 60.0], [250.0, 400.0]], 2, 10.0)
    aid = GnssAid(GnssConfig(), index, fixes)
    near = aid.cue(0, np.array([50, 51]), np.array([1.0, 2.0]))
    far = aid.cue(1, np.array([50, 51]), np.array([1.0, 2.0]))
    assert near is not None and far is not None
    assert 1.0 < near[3] < far[3] == pytest.approx(math.exp(8.0))
    # a hit without a mapped position: it could be anywhere, the unmapped place is not raised
    index = PositionIndex(300, [(0, rows)], map_sigma=10.0)
    aid = GnssAid(GnssConfig(), index, fixes)
    cue = aid.cue(1, np.array([50, 250]), np.array([1.0, 2.0]))
    assert cue is not None and cue[3] == 1.0


# --- the facade: localise, merge --------------------------------------------------------------
def test_without_fixes_nothing_changes(twins):
    path, query, truth = twins
    with SprintMap.open(path, readonly=True) as m:
        plain, _ = m.localize(query, smooth=True)
        again, _ = m.localize(query, smooth=True, fixes=None)
    assert plain == again
    assert all(math.isnan(d.gnss_dist_m) for d in plain)
    assert all(d.to_dict()["gnss_dist_m"] is None for d in plain)


def test_identical_twins_are_resolved_by_gnss(twins):
    path, query, truth = twins
    fixes = fixes_for(truth, 6)
    assert np.isnan(fixes[:, 0]).any()  # the receiver dropped out somewhere
    assert np.nanmax(np.hypot(*(fixes[:, :2] - truth).T)) > 50  # and a multipath jump
    with SprintMap.open(path, readonly=True) as m:
        image_only, _ = m.localize(query, smooth=True)
        aided, _ = m.localize(query, smooth=True, fixes=fixes)
        merged = m.service.select_merges(aided)
        refused = m.service.select_merges(image_only)
        street0 = m.sequence_by_name("street-0").seq_id
    # image only: two identical streets, the lookalike tests refuse both
    assert not refused.any()
    # GNSS: the street the vehicle drives is merged, its twin never
    assert merged.sum() >= 60
    assert {aided[i].seq_id for i in np.flatnonzero(merged)} == {street0}
    assert all(abs(aided[i].image_id - (20 + i)) <= 3 for i in np.flatnonzero(merged))
    dists = [d.gnss_dist_m for d in aided if d.is_match and not math.isnan(d.gnss_dist_m)]
    assert dists and np.median(dists) < 40


@pytest.fixture
def one_street(tmp_path):
    """A map of one street, mapped with simulated fixes, and a drive along it."""
    rng = np.random.default_rng(4)
    places = street(rng)
    path = tmp_path / "street.map"
    with SprintMap.create(path, MapConfig(dim=DIM)) as m:
        m.add_sequence(driven(places, rng, 0.3), name="street",
                       positions=fixes_for(along(0.0), 30)[:, :2])
    return path, driven(places[20:140], rng), along(0.0, 120, start=20)


@pytest.mark.parametrize("offset_m", [120.0, 400.0])
def test_a_decision_far_from_its_fix_is_never_merged(one_street, offset_m):
    """A receiver that puts the vehicle ``offset_m`` beside the street it drives: the images
    match the street, which image only merges; nothing beyond the gate of a fix merges."""
    path, query, truth = one_street
    fixes = fixes_for(truth + [0.0, offset_m], 31)
    with SprintMap.open(path, readonly=True) as m:
        image_only, _ = m.localize(query, smooth=True)
        aided, _ = m.localize(query, smooth=True, fixes=fixes)
        assert m.service.select_merges(image_only).sum() >= 80
        merged = m.service.select_merges(aided)
    fixed = ~np.isnan(fixes[:, 0])
    assert not merged[fixed].any()
    for d in aided:
        if d.is_match and not math.isnan(d.gnss_dist_m):
            assert d.gnss_dist_m > 42.5 and not d.confirmed  # the gate of two 10 m fixes
    # each decision with a fix (not dropped as off the track) says how far its place lies
    kept = consistent(validate_fixes(fixes, None, 10.0), GnssConfig())
    assert all(not math.isnan(d.gnss_dist_m) for d, f in zip(aided, kept, strict=True)
               if f and d.is_match)


def test_a_fix_far_from_every_mapped_place_raises_novel_prob(one_street):
    path, query, truth = one_street
    fixes = fixes_for(truth + [0.0, -3000.0], 9)
    fixed = ~np.isnan(fixes[:, 0])
    with SprintMap.open(path, readonly=True) as m:
        plain, _ = m.localize(query, smooth=True)
        away, _ = m.localize(query, smooth=True, fixes=fixes)
        near, _ = m.localize(query, smooth=True, fixes=fixes_for(truth, 9))
    assert np.mean([d.novel_prob for d in plain]) < 0.1
    assert np.mean([d.novel_prob for d in near]) < 0.1
    assert np.median([d.novel_prob for d, f in zip(away, fixed, strict=True) if f]) > 0.9


def test_a_retrieval_miss_near_a_good_fix_is_recovered(tmp_path):
    """Retrieval with k = 1 sees only a lookalike street (a better image match: the query is
    closer to it); the vertices near the fix join the hits and the HMM follows the street the
    vehicle is on."""
    rng = np.random.default_rng(5)
    places = street(rng)
    lookalike = places + rng.normal(0, 0.4, places.shape).astype(np.float32)
    path = tmp_path / "miss.map"
    with SprintMap.create(path, MapConfig(dim=DIM)) as m:
        m.add_sequence(driven(places, rng, 1.5), name="street",
                       positions=fixes_for(along(0.0), 21)[:, :2])
        m.add_sequence(lookalike, name="lookalike",
                       positions=fixes_for(along(900.0), 22)[:, :2])
        query = driven(lookalike[20:140], rng, 0.2)  # the drive looks like the lookalike...
        truth = along(0.0, 120, start=20)  # ...but is on the street
        fixes = fixes_for(truth, 23)
        image_only, _ = m.localize(query, smooth=True, k=1)
        aided, _ = m.localize(query, smooth=True, k=1, fixes=fixes)
        on_street = m.sequence_by_name("street").seq_id
    fixed = ~np.isnan(fixes[:, 0])
    # The most probable place (``best``) follows the street; the answer is that place only
    # where the map knows the images (one rule for an answer: here, mostly "no match").
    assert np.mean([d.best is not None and d.best[0] == on_street for d in image_only]) < 0.1
    assert np.mean([d.best is not None and d.best[0] == on_street
                    for d, f in zip(aided, fixed, strict=True) if f]) > 0.8
    assert all(d.seq_id in (None, d.best[0]) for d in aided if d.best is not None)


def test_ingest_with_fixes_reports_gnss_dist_and_merges(twins):
    path, query, truth = twins
    fixes = fixes_for(truth, 11)
    with SprintMap.open(path) as m:
        result = m.ingest(query, name="drive", positions=fixes[:, :2], fixes=fixes)
        stored = m.positions(result.added.sequence.seq_id)
    assert result.merged.sum() >= 60
    out = result.to_dict()["decisions"]
    assert any(d["gnss_dist_m"] is not None for d in out)
    assert all(d["gnss_dist_m"] is None for d, f in zip(out, fixes, strict=True)
               if np.isnan(f[0]))
    assert stored is not None and np.isnan(stored[np.isnan(fixes[:, 0]), 0]).all()


@pytest.mark.parametrize("bad", ["short", "long", "nan", "sigma", "range"])
def test_bad_fixes_leave_the_map_unchanged(twins, bad):
    path, query, truth = twins
    fixes = fixes_for(truth, 12)
    fixes = {"short": fixes[:-1], "long": np.r_[fixes, fixes[:1]],
             "nan": np.where(np.arange(len(fixes))[:, None] == 5, [np.nan, 1.0, 10.0], fixes),
             "sigma": np.where(np.arange(len(fixes))[:, None] == 5, [1.0, 1.0, 0.0], fixes),
             "range": fixes + [1e9, 0.0, 0.0]}[bad]
    with SprintMap.open(path) as m:
        before = m.stats()
        with pytest.raises(InputError, match="GNSS fixes"):
            m.ingest(query, name="drive", fixes=fixes)
        with pytest.raises(InputError, match="GNSS fixes"):  # streamed: checked at the end
            m.ingest(iter([query[:50], query[50:]]), name="drive", fixes=fixes)
        assert m.stats() == before


def test_localize_and_ingest_commands_read_fixes_from_positions(one_street, tmp_path):
    from click.testing import CliRunner

    from sprint_map.cli.main import main

    path, query, truth = one_street
    fixes = fixes_for(truth, 40)
    np.save(tmp_path / "drive.npy", query)
    csv = tmp_path / "drive.csv"  # frames without a fix have no row
    csv.write_text("frame,x,y,sigma_m\n" + "".join(
        f"{i},{x},{y},{s}\n" for i, (x, y, s) in enumerate(fixes.tolist()) if not math.isnan(x)))
    out = CliRunner().invoke(main, ["localize", str(path), str(tmp_path / "drive.npy"),
                                    "--smooth", "--positions", str(csv), "--json"])
    assert out.exit_code == 0, out.output
    decisions = json.loads(out.output)["decisions"]
    dists = [d["gnss_dist_m"] for d in decisions]
    assert all(d is None for d, f in zip(dists, fixes, strict=True) if math.isnan(f[0]))
    assert np.median([d for d in dists if d is not None]) < 30
    out = CliRunner().invoke(main, ["ingest", str(path), str(tmp_path / "drive.npy"),
                                    "--positions", str(csv), "--json"])
    assert out.exit_code == 0, out.output
    result = json.loads(out.output)
    assert result["edges_added"] > 0
    assert any(d["gnss_dist_m"] is not None for d in result["decisions"])
    with SprintMap.open(path, readonly=True) as m:
        stored = m.positions(result["seq_id"])
    assert stored is not None and np.isnan(stored[np.isnan(fixes[:, 0]), 0]).all()


def test_a_lag_refuses_fixes_with_one_clear_error(one_street, tmp_path):
    from click.testing import CliRunner

    from sprint_map.cli.main import main

    path, query, truth = one_street
    fixes = fixes_for(truth, 41)
    with SprintMap.open(path, readonly=True) as m:
        with pytest.raises(InputError, match="GNSS fixes are not supported with a lag"):
            m.localize(query, lag=3, fixes=fixes)
        lagged, _ = m.localize(query, lag=3)  # without fixes the lag still answers
    assert len(lagged) == len(query)
    np.save(tmp_path / "drive.npy", query)
    csv = tmp_path / "drive.csv"
    csv.write_text("frame,x,y\n0,0,0\n")
    out = CliRunner().invoke(main, ["localize", str(path), str(tmp_path / "drive.npy"),
                                    "--lag", "3", "--positions", str(csv)])
    assert out.exit_code != 0 and "--lag does not weigh GNSS fixes" in out.output
