"""Admission (``--admission novel``): which frames a drive stores, what it records instead."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sprint_map import MapConfig
from sprint_map.localize.localizer import FrameDecision
from sprint_map.map import SprintMap
from sprint_map.merge.admission import (
    COPY_STEPS,
    Admission,
    drive_step,
    place_distances,
    plan_admission,
    stored_frames,
)
from sprint_map.merge.commit import merge_edges
from sprint_map.storage.records import EdgeSpec
from sprint_map.testing.crash import CRASH_ENV
from tests.helpers.worlds import road_places, traverse, unit

# --- the plan, from decisions ----------------------------------------------------------------


def matched(frame: int, image: int, seq: int = 0, prob: float = 0.9) -> FrameDecision:
    return FrameDecision(frame, seq, image, prob, distance=0.25)


def unmatched(frame: int) -> FrameDecision:
    return FrameDecision(frame, None, None, 0.1, novel_prob=0.9)


NOVEL = Admission(mode="novel", min_skip=5, margin=0)
STEP = 0.5  # the drive's median squared step: a place within it is a view alike


def detour_decisions() -> tuple[list[FrameDecision], np.ndarray, np.ndarray]:
    """40 frames matched to sequence 0 (images 10..49), 30 unmatched, 30 matched (60..89);
    the matched ones as close to their place as to their next frame."""
    ds = ([matched(i, 10 + i) for i in range(40)] + [unmatched(i) for i in range(40, 70)]
          + [matched(i, i - 10) for i in range(70, 100)])
    merged = np.array([d.seq_id is not None for d in ds])
    return ds, merged, np.where(merged, 0.4, np.inf)


def test_all_stores_every_frame_with_the_merge_edges():
    ds, merged, dist = detour_decisions()
    plan = plan_admission(ds, merged, Admission(), True, dist, STEP)
    assert plan.stored.all() and plan.image_of.tolist() == list(range(100))
    assert plan.edges == merge_edges(ds, merged, True) and not plan.sightings


def test_novel_stores_the_detour_stitched_into_the_map():
    ds, merged, dist = detour_decisions()
    plan = plan_admission(ds, merged, NOVEL, True, dist, STEP)
    assert np.flatnonzero(plan.stored).tolist() == list(range(40, 70))
    assert plan.image_of[40] == 0 and plan.image_of[69] == 29 and plan.image_of[0] == -1
    # where the drive came from (frame 39 on image 49) and where it went (frame 70 on 60)
    assert plan.edges == [EdgeSpec((0, 49), (None, 0), 0.9, 0),
                          EdgeSpec((None, 29), (0, 60), 0.9, 29)]
    assert [(s, i) for s, i, _ in plan.sightings] == (
        [(0, 10 + i) for i in range(40)] + [(0, i - 10) for i in range(70, 100)])
    assert all(d == 0.4 for _, _, d in plan.sightings)  # each frame's distance to its place
    # without place distances, or a scale for them, nothing is known to be redundant
    assert plan_admission(ds, merged, NOVEL, True).stored.all()
    assert plan_admission(ds, merged, NOVEL, True, dist, math.inf).stored.all()


def test_a_new_appearance_of_a_known_place_is_stored_with_its_merge_edges():
    # merged (the sequence found it) but its views look unlike the frame: farther than a step
    ds = [matched(i, i) for i in range(60)]
    dist = np.where((np.arange(60) >= 20) & (np.arange(60) < 50), 3 * STEP, 0.5 * STEP)
    dist[25] = np.nan  # unknown: not known to be redundant
    plan = plan_admission(ds, np.ones(60, dtype=bool), NOVEL, False, dist, STEP)
    assert np.flatnonzero(plan.stored).tolist() == list(range(20, 50))
    merge = [e for e in plan.edges if e.src[0] is None and e.dst == (0, e.src[1] + 20)]
    assert len(merge) == 30  # each stored merged frame keeps its edge to its place
    assert len(plan.sightings) == 30


@pytest.mark.parametrize(("pattern", "expected"), [
    ("RRRRRRRRRRSSRRRRRRRRRR", "RRRRRRRRRRRRRRRRRRRRRR"),  # a 2-frame blip is not stored
    ("SSSSSSSSSSRRSSSSSSSSSS", "SSSSSSSSSSSSSSSSSSSSSS"),  # a 2-frame gap is stored through
    ("SSRRRRRRRRRRRRRRRRRRRR", "RRRRRRRRRRRRRRRRRRRRRR"),  # at the ends too
    ("RRRRRRRRRRSSSSSSRRRRRR", "RRRRRRRRRRSSSSSSRRRRRR"),  # runs of min_run / min_skip stay
    ("SSS", "SSS"), ("RRR", "RRR"),  # a short drive is one run either way
])
def test_short_runs_are_absorbed(pattern, expected):
    ds = [matched(i, i) if c == "R" else unmatched(i) for i, c in enumerate(pattern)]
    merged = np.array([c == "R" for c in pattern])
    got = stored_frames(ds, merged, NOVEL, np.where(merged, 0.5, np.inf))
    assert "".join("S" if s else "R" for s in got) == expected


def test_the_default_skips_only_stretches_a_merge_run_long():
    ds = [matched(i, i) for i in range(60)]
    merged = np.ones(60, dtype=bool)

    def stored(far: list[range]) -> list[int]:
        closeness = np.full(60, 0.5)  # alike, no copies
        for r in far:
            closeness[r] = 5.0
        return np.flatnonzero(stored_frames(ds, merged, Admission(mode="novel", margin=0),
                                            closeness)).tolist()

    # 20 redundant frames before, 30 after: both skipped
    assert stored([range(20, 30)]) == list(range(20, 30))
    # 15 redundant frames between two stored runs, 10 at the end: stored through
    assert stored([range(20, 30), range(45, 50)]) == list(range(20, 60))
    # 20 between them and 20 at the end: skipped (at least a merge run long); 5 at the start not
    assert stored([range(5, 15), range(35, 40)]) == list(range(0, 15)) + list(range(35, 40))


def test_each_stored_run_takes_a_margin_of_redundant_frames():
    ds = [matched(i, i) for i in range(100)]
    closeness = np.full(100, 0.5)
    closeness[40:60] = 5.0
    got = stored_frames(ds, np.ones(100, dtype=bool), Admission(mode="novel"), closeness)
    assert np.flatnonzero(got).tolist() == list(range(30, 70))  # the default margin: 10
    closeness[:] = 0.0  # nothing to store: no margin either
    assert not stored_frames(ds, np.ones(100, dtype=bool), Admission(mode="novel"),
                             closeness).any()


def test_a_frame_the_rule_did_not_merge_is_stored():
    ds = [matched(i, i) for i in range(30)]
    merged = np.ones(30, dtype=bool)
    merged[10:20] = False  # the rule refused these: localisation is not sure there
    alike = np.full(30, 0.5)  # within a step of their place
    assert np.flatnonzero(stored_frames(ds, merged, NOVEL, alike)).tolist() == list(
        range(10, 20))
    # unless the map holds a copy of the frame itself: storing it again adds nothing
    alike[10:20] = COPY_STEPS
    assert not stored_frames(ds, merged, NOVEL, alike).any()
    alike[15] = np.inf  # one frame without a copy: a blip shorter than min_run, not stored
    assert not stored_frames(ds, merged, NOVEL, alike).any()


def test_a_copy_of_an_unmatched_frame_is_not_stored_again():
    ds = [matched(i, i) for i in range(30)]
    ds[10:20] = [unmatched(i) for i in range(10, 20)]  # the filter found no place here
    merged = np.array([d.is_match for d in ds])
    closeness = np.where(merged, 0.5, np.inf)
    assert np.flatnonzero(stored_frames(ds, merged, NOVEL, closeness)).tolist() == list(
        range(10, 20))  # 10 novel frames: stored
    closeness[10:20] = COPY_STEPS  # but the map holds a copy of each of them
    assert not stored_frames(ds, merged, NOVEL, closeness).any()


def test_drive_step_and_place_distances():
    rows = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 2.0], [1.0, 3.0]], dtype=np.float32)
    assert drive_step(rows) == 1.0 and drive_step(rows[:1]) == math.inf
    stored = {0: np.array([[5.0, 5.0], [0.5, 0.0], [1.0, 2.5], [9.0, 9.0]], dtype=np.float32)}
    ds = [matched(0, 0), matched(1, 0), matched(2, 3), unmatched(3)]
    got = place_distances(rows, ds, np.array([True, True, False, False]),
                          lambda s, a, b: stored[s][a:b], lambda s: len(stored[s]), radius=1)
    # frame 0 nearest to image 1 of the decided 0 +- 1; frame 1 too; the others not merged
    assert got.tolist() == [0.25, 0.25, math.inf, math.inf]
    gone = place_distances(rows, ds, np.ones(4, dtype=bool), lambda s, a, b: stored[s][a:b],
                           lambda s: 0)  # the sequence was removed meanwhile
    assert np.isinf(gone).all()


def test_a_copy_of_the_frame_one_edge_from_its_place_counts_as_its_place():
    rows = np.array([[0.0, 0.0], [4.0, 0.0]], dtype=np.float32)
    stored = {0: np.array([[3.0, 3.0], [3.0, 4.0], [3.0, 5.0]], dtype=np.float32),
              1: np.array([[0.01, 0.0], [9.0, 9.0]], dtype=np.float32),
              2: np.array([[4.0, 0.5]], dtype=np.float32)}
    edges = {(0, 1): [(1, 0), (2, 0)]}  # image 1 of sequence 0 is joined to those

    def linked(seq, a, b):
        return [end for i in range(a, b) for end in edges.get((seq, i), [])]

    ds = [matched(0, 1), matched(1, 1)]

    def distances(limit, merged=(True, True), copies=None):
        return place_distances(rows, ds, np.array(merged), lambda s, a, b: stored[s][a:b],
                               lambda s: len(stored[s]), radius=0, linked=linked,
                               copy_limit=limit, copies=copies).tolist()

    # frame 0 has a copy one edge away (1e-4 <= 0.01); frame 1's linked views are no copies
    # (0.25 is the nearer one): its place is the decided image alone
    assert distances(0.01) == [pytest.approx(1e-4), 17.0]
    assert distances(0.0) == [25.0, 17.0]  # no copy looked for
    # not merged: only a copy counts
    assert distances(0.01, merged=(False, False)) == [pytest.approx(1e-4), math.inf]


@pytest.mark.parametrize("merged", [(True, True), (False, False)])
def test_a_best_hit_that_is_a_copy_counts_wherever_it_lies(merged):
    rows = np.array([[0.0, 0.0], [4.0, 0.0], [7.0, 7.0]], dtype=np.float32)
    stored = {0: np.array([[3.0, 3.0], [3.0, 4.0]], dtype=np.float32)}
    ds = [matched(0, 1), matched(1, 0), unmatched(2)]

    def distances(copies):
        return place_distances(rows, ds, np.array([*merged, False]),
                               lambda s, a, b: stored[s][a:b], lambda s: len(stored[s]),
                               radius=0, copy_limit=0.01, copies=np.array(copies)).tolist()

    # each frame's best retrieval hit (the distance to its stored row): copies of frames 0 and
    # 2 (at most copy_limit), frame 2 matched nowhere; frame 1's hit is no copy
    place = [25.0, 10.0] if merged[0] else [math.inf, math.inf]
    assert distances([1e-3, 0.5, 2e-3]) == [pytest.approx(1e-3), place[1], pytest.approx(2e-3)]
    assert distances([math.inf] * 3) == [*place, math.inf]


@pytest.mark.parametrize("bad", [{"mode": "some"}, {"max_step_ratio": -1.0},
                                 {"max_step_ratio": math.inf}, {"min_run": 0},
                                 {"min_run": 2.5}, {"min_skip": 0}, {"margin": -1}])
def test_bad_admission_values_are_refused(bad):
    with pytest.raises(ValueError, match="admission"):
        Admission(**bad)


# --- on a map -------------------------------------------------------------------------------

DIM = 64


@pytest.fixture
def world():
    """A seeded rng, a drive of 300 frames along a road and one of 100 along a detour, each
    under its own appearance."""
    rng = np.random.default_rng(0)
    road = traverse(rng, road_places(rng, 400, DIM, corr=0.9), 0, 300, 0.3, speed=(1, 1))[0]
    detour = traverse(rng, road_places(rng, 120, DIM, corr=0.9), 0, 100, 0.3, speed=(1, 1))[0]
    return rng, road, detour


def again(rng, rows):
    """``rows`` driven again under the same appearance: a little noise."""
    return unit(rows + 0.02 * rng.standard_normal(rows.shape))


def detour_drive(rng, road, detour):
    """100 frames on the road (its frames 0..99), 100 on the detour, 100 back on the road
    (150..249), all under the appearances the drives had."""
    return np.concatenate([again(rng, road[:100]), again(rng, detour),
                           again(rng, road[150:250])])


@pytest.fixture
def novel_map(tmp_path, world):
    _, road, _ = world
    m = SprintMap.create(tmp_path / "m.map", MapConfig(dim=DIM).replace(
        admission={"mode": "novel"}))
    m.ingest(road, name="first")
    yield m
    m.close()


def test_a_drive_already_in_the_map_stores_nothing_and_counts_its_sightings(novel_map, world):
    rng, road, _ = world
    rows = again(rng, road)
    result = novel_map.ingest(rows, name="again")
    assert result.added is None and result.frames == 300
    assert result.frames_stored <= 3  # at most 1 %
    out = result.to_dict()
    assert out["seq_id"] is None and out["name"] == "again" and out["frames_skipped"] == 300
    assert all(d["stored_as"] is None for d in out["decisions"])
    seen = novel_map.store.sighting(0, 150)
    assert seen is not None and seen.count == 1 and seen.last_drive == "again"
    novel_map.ingest(rows, name="again-2")
    assert novel_map.store.sighting(0, 150).count == 2
    assert novel_map.stats()["sequences"] == 1 and novel_map.check().ok


@pytest.mark.parametrize("dusk", ["first half", "second half"])
def test_a_drive_stored_in_part_and_ingested_again_stores_nothing(tmp_path, dusk):
    # Half of the drive is the mapped road at dusk (stored, merged to the road), the other half
    # the road as the map saw it (left out). Ingested again, every frame has a copy in the map:
    # in the drive's own stored half, or in the road.
    rng = np.random.default_rng(0)
    road = traverse(rng, road_places(rng, 400, DIM, corr=0.9), 0, 300, 0.3, speed=(1, 1))[0]
    drive = unit(road + 0.01 * rng.standard_normal(road.shape))
    dark = slice(0, 150) if dusk == "first half" else slice(150, 300)
    drive[dark] = unit(drive[dark] + 0.8 * unit(rng.standard_normal(DIM)))
    with SprintMap.create(tmp_path / "m.map", MapConfig(dim=DIM).replace(
            admission={"mode": "novel"})) as m:
        m.ingest(road, name="road")
        first = m.ingest(drive, name="drive")
        assert 150 <= first.frames_stored <= 170  # the dusk half and its margin
        again = m.ingest(unit(drive + 0.01 * rng.standard_normal(drive.shape)), name="again")
        assert again.frames_stored <= 3 and int(np.sum(again.merged)) >= 290
        assert m.check().ok


@pytest.mark.parametrize(("gap", "copies", "stored"), [
    (21, "both sides", False),  # what the stored drive left out, between its stored frames
    (21, "both sides, a merged frame alike inside", False),
    (39, "both sides", False),
    (40, "both sides", True),  # as long as min_skip and two margins: not left out before
    (21, "before", True),  # the drive goes on into what the map lacks
    (21, "after", True),
])
def test_a_short_stretch_between_copies_is_what_the_stored_drive_left_out(gap, copies, stored):
    ds = [matched(i, i) for i in range(140)]
    merged = np.ones(140, dtype=bool)
    merged[50:50 + gap] = False  # a run too short to merge, unlike its place's views
    closeness = np.full(140, 5.0)
    if copies != "after":
        closeness[:50] = COPY_STEPS
    if copies != "before":
        closeness[50 + gap:] = COPY_STEPS
    if copies.endswith("inside"):  # redundant, but no copy: the stretch still ends at copies
        merged[60], closeness[60] = True, 0.5
    got = stored_frames(ds, merged, Admission(mode="novel"), closeness)
    assert got[50:50 + gap].all() == stored


@pytest.mark.parametrize("end", ["start", "end"])
@pytest.mark.parametrize(("near", "stored"), [
    (0.5, False),  # as alike as the next frame, next to copies: what the stored drive left out
    (5.0, True),  # unlike anything the map holds: the drive goes on into what the map lacks
    (None, True),  # no best hits known: only copies and merged frames are redundant
])
def test_an_alike_stretch_next_to_copies_at_a_drive_end_is_not_stored(end, near, stored):
    ds = [matched(i, i) for i in range(100)]
    merged = np.ones(100, dtype=bool)
    gap = slice(0, 25) if end == "start" else slice(75, 100)
    merged[gap] = False  # a run the rule did not merge
    closeness = np.full(100, COPY_STEPS)
    closeness[gap] = 5.0  # nothing alike in its decided place
    nearest = None if near is None else np.where(closeness <= COPY_STEPS, COPY_STEPS, near)
    if nearest is not None:
        nearest[gap.start + 12] = 5.0  # one frame unlike: a blip, not a stretch of its own
    got = plan_admission(ds, merged, Admission(mode="novel"), True, closeness * STEP, STEP,
                         None if nearest is None else nearest * STEP).stored
    assert got[gap].all() == stored and got[gap].any() == stored
    if near is not None and not stored:  # copies on neither side: stored as before
        assert stored_frames(ds, merged, Admission(mode="novel"), np.full(100, 5.0),
                             nearest=np.full(100, near)).all()


@pytest.mark.parametrize("hits", ["copies", "none", "removed"])
def test_frames_whose_best_hit_is_a_copy_are_not_stored_even_unmatched(novel_map, world, hits):
    # 100 frames of the mapped road again, which the filter matched nowhere; their best
    # retrieval hits are the road's own views (vertices 0..99): copies of them
    rng, road, _ = world
    rows = again(rng, road[:100]) if hits != "none" else unit(
        road[:100] + 0.5 * rng.standard_normal((100, DIM)))  # far from any view
    if hits == "removed":
        novel_map.remove_sequences([0])
    decisions = [FrameDecision(i, None, None, 0.1, novel_prob=0.9, distance=1e-4, nearest=i)
                 for i in range(100)]
    with novel_map.service.begin_drive("unmatched") as drive:
        drive.append(rows)
        done = drive.commit(decisions)
    stored = 0 if done.plan is None else done.plan.frames_stored
    assert stored == (0 if hits == "copies" else 100)
    assert done.sightings == 0 and novel_map.check().ok


def test_a_detour_is_stored_stitched_and_found_by_the_next_drive(novel_map, world):
    rng, road, detour = world
    result = novel_map.ingest(detour_drive(rng, road, detour), name="detour")
    assert result.added is not None
    seq = result.added.sequence.seq_id
    stored = [f for f in range(300) if result.stored_as(f) is not None]
    # the detour (frames 100..199) and the default margin of 10 frames either side
    assert 110 <= len(stored) <= 130 and set(range(95, 205)) <= set(stored)
    assert result.stored_as(150) == (seq, 150 - stored[0])
    out = result.to_dict()
    assert (out["frames"], out["frames_stored"]) == (300, len(stored))
    assert out["decisions"][150]["stored_as"] == [seq, 150 - stored[0]]
    ends = {(e.src_seq, e.dst_seq) for e in novel_map.edges(seq)}
    assert ends == {(0, seq), (seq, 0)}  # in from the road and back out to it
    # the next drive on the detour is localised on it, and stores (almost) nothing
    decisions, _ = novel_map.localize(detour_drive(rng, road, detour), smooth=True)
    assert sum(d.seq_id == seq for d in decisions[100:200]) >= 90
    again = novel_map.ingest(detour_drive(rng, road, detour), name="detour-2")
    assert again.frames_stored <= 3
    assert novel_map.check().ok


def test_remove_and_compact_keep_sightings_consistent(novel_map, world):
    rng, road, detour = world
    seq = novel_map.ingest(detour_drive(rng, road, detour), name="detour").added.sequence.seq_id
    novel_map.ingest(detour_drive(rng, road, detour), name="detour-2")
    assert novel_map.store.sighting(seq, 50) is not None
    novel_map.compact()
    assert novel_map.store.sighting(seq, 50) is not None and novel_map.check().ok
    novel_map.remove_sequences([seq])
    report = novel_map.check()
    assert report.ok and report.checked["sightings"] > 0  # the road's, not the detour's
    assert novel_map.store.sighting(0, 200) is not None


def test_a_map_without_admission_stores_every_frame(tmp_path, world):
    rng, road, _ = world
    with SprintMap.create(tmp_path / "m.map", MapConfig(dim=DIM)) as m:
        m.ingest(road, name="first")
        result = m.ingest(again(rng, road), name="again")
        out = result.to_dict()
        assert (out["frames"], out["frames_stored"], out["frames_skipped"]) == (300, 300, 0)
        assert out["decisions"][7]["stored_as"] == [1, 7] and out["sightings"] == 0


# --- a kill at any instant of an admitted commit ----------------------------------------------

KILL_SCRIPT = """
import sys
import numpy as np
from sprint_map.map import SprintMap
path, which = sys.argv[1], sys.argv[2]
with SprintMap.open(path) as m:
    rows = np.load(sys.argv[3])
    m.ingest(rows, name=which)
"""


@pytest.mark.parametrize(("which", "point"), [
    ("again", "sightings.before_commit"), ("again", "sightings.committed"),
    ("detour", "add.shards_written"), ("detour", "add.before_commit"),
    ("detour", "add.committed"),
])
def test_a_kill_leaves_the_drive_whole_or_absent(novel_map, world, tmp_path, which, point):
    rng, road, detour = world
    rows = again(rng, road) if which == "again" else detour_drive(rng, road, detour)
    np.save(tmp_path / "rows.npy", rows)
    path = novel_map.path
    novel_map.close()
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, CRASH_ENV: point, "PYTHONPATH": str(root)}
    done = subprocess.run([sys.executable, "-c", KILL_SCRIPT, str(path), which,
                           str(tmp_path / "rows.npy")], env=env, cwd=root, timeout=120)
    assert done.returncode == -9
    after = point.endswith("committed")
    with SprintMap.open(path) as m:
        assert m.check().ok
        seen = m.store.sighting(0, 200)
        assert (seen is not None) == after  # the sightings count with the drive or not at all
        names = [s.name for s in m.sequences()]
        assert ("detour" in names) == (after and which == "detour")
        m.ingest(rows, name=which + "-retry")  # the writer goes on
        assert m.check().ok


def test_unmerge_of_an_admitted_drive_revokes_its_stitches(novel_map, world):
    rng, road, detour = world
    seq = novel_map.ingest(detour_drive(rng, road, detour), name="detour").added.sequence.seq_id
    assert novel_map.edges(seq)
    result = novel_map.unmerge("detour")
    assert result.edges_removed >= 2 and not novel_map.edges(seq)
    assert novel_map.component_of(seq) != novel_map.component_of(0) and novel_map.check().ok
