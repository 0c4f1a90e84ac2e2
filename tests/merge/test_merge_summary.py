"""``summarize``: a kept-everything map without the views it repeats (merge/summary.py, and
storage/reduction.py through compaction)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from sprint_map import MapConfig
from sprint_map.map import SprintMap
from sprint_map.merge.summary import plan_summary
from sprint_map.storage.generation import CURRENT_NAME
from sprint_map.storage.sightings import scan_sightings
from sprint_map.testing.crash import CRASH_ENV, SUMMARIZE_POINTS
from tests.helpers.worlds import road_places, traverse, unit

DIM = 64


@pytest.fixture
def world():
    """A seeded rng, 300 frames along a road and 100 along a detour, each under its own
    appearance."""
    rng = np.random.default_rng(0)
    road = traverse(rng, road_places(rng, 400, DIM, corr=0.9), 0, 300, 0.3, speed=(1, 1))[0]
    detour = traverse(rng, road_places(rng, 120, DIM, corr=0.9), 0, 100, 0.3, speed=(1, 1))[0]
    return rng, road, detour


def again(rng, rows, noise=0.02):
    """``rows`` driven again under the same appearance: a little noise."""
    return unit(rows + noise * rng.standard_normal(rows.shape))


def detour_drive(rng, road, detour):
    """The road's frames 0..99, the detour, the road's frames 150..249."""
    return np.concatenate([again(rng, road[:100]), again(rng, detour),
                           again(rng, road[150:250])])


def xy(n, offset=0.0):
    return np.column_stack([np.arange(n) + offset, np.zeros(n)])


@pytest.fixture
def everything(tmp_path, world):
    """A map keeping every frame: the road, the road again, the detour drive twice."""
    rng, road, detour = world
    m = SprintMap.create(tmp_path / "m.map", MapConfig(dim=DIM))
    m.ingest(road, name="road", positions=xy(300))
    m.ingest(again(rng, road), name="again", positions=xy(300))
    m.ingest(detour_drive(rng, road, detour), name="detour", positions=xy(300, 1000))
    m.ingest(detour_drive(rng, road, detour), name="detour-2", positions=xy(300, 2000))
    yield m
    m.close()


def test_a_repeated_drive_goes_and_a_detour_keeps_its_new_stretch(everything):
    m = everything
    frames_before = {s.name: s.length for s in m.sequences()}
    m.store.record_sightings("probe", [(1, 50, 0.0), (1, 50, 0.0)])  # "again" seen twice
    report = m.summarize()
    assert {k: report[k] for k in ("vertices_before", "sequences_before",
                                   "sequences_after")} == {"vertices_before": 1200,
                                                           "sequences_before": 4,
                                                           "sequences_after": 2}
    seqs = {s.name: s for s in m.sequences()}
    assert set(seqs) == {"road", "detour"} and seqs["road"].length == frames_before["road"]
    # the detour (its frames 100..199) and a margin of 10 frames either side
    assert 110 <= seqs["detour"].length <= 130
    assert report["vertices_after"] == 300 + seqs["detour"].length == m.stats()["vertices"]
    # kept frames keep their positions, in order
    pos = m.positions(seqs["detour"].seq_id)
    assert pos is not None and np.all(np.diff(pos[:, 0]) == 1) and 1090 <= pos[0, 0] <= 1100
    # stitched into the road and back out of it; the dropped drives' views counted as seen
    ends = {(e.src_seq, e.dst_seq) for e in m.edges(seqs["detour"].seq_id)}
    assert ends == {(0, seqs["detour"].seq_id), (seqs["detour"].seq_id, 0)}
    seen = m.store.sighting(0, 50)
    assert seen is not None and seen.count >= 2  # "again", "detour" and "detour-2" saw it
    dropped = 1200 - report["vertices_after"]
    assert dropped - 5 <= report["sightings"] <= dropped  # each but a smoothed blip's
    # the probe's two sightings of a dropped view moved to its stand-in: every count is kept
    with m.store.env.read() as txn:
        scan = scan_sightings(txn, m.store.env, {s.seq_id: s.length for s in m.sequences()})
    assert scan.total == report["sightings"] + 2 and not scan.problems
    report = m.check()
    assert report.ok and report.checked["sightings"] > 0, report.violations


def test_the_summary_localises_a_fresh_drive_as_before(everything, world):
    rng, road, detour = world
    fresh = detour_drive(rng, road, detour)
    m = everything
    m.summarize()
    detour_seq = m.sequence_by_name("detour").seq_id
    decisions, _ = m.localize(fresh, smooth=True)
    assert sum(d.seq_id == detour_seq for d in decisions[100:200]) >= 90
    assert sum(d.seq_id == 0 and abs(d.image_id - f) <= 2 for f, d in enumerate(decisions[:90])
               ) >= 85
    # a new drive along it stores nothing new on a map that admits only what it lacks
    result = m.ingest(fresh, name="fresh")
    assert result.frames_stored == 300  # this map keeps everything: summarise again
    assert m.summarize()["vertices_after"] == 300 + m.sequence_by_name("detour").length


def test_per_place_keeps_k_drives_views(tmp_path, world):
    rng, road, _ = world
    with SprintMap.create(tmp_path / "m.map", MapConfig(dim=DIM)) as m:
        for name in ("a", "b", "c", "d"):
            m.ingest(again(rng, road), name=name)
        assert plan_summary(m.store, 1).vertices_after == 300
        assert plan_summary(m.store, 2).vertices_after == 600
        assert m.summarize(per_place=3)["vertices_after"] == 900
        assert [s.name for s in m.sequences()] == ["a", "b", "c"] and m.check().ok


def test_remove_unmerge_and_compact_work_on_a_summary(everything):
    m = everything
    m.summarize()
    detour = m.sequence_by_name("detour").seq_id
    added = [e for e in m.edges(detour) if e.added_by == detour]
    result = m.unmerge("detour")
    assert result.edges_removed == len(added) > 0  # its merge edges and its stitches
    # the edges "detour-2" added, moved onto the views standing for its frames, stay
    assert {e.added_by for e in m.edges(detour)} == {3} and m.check().ok
    m.remove_sequences(["detour"])
    m.compact()
    assert m.stats()["vertices"] == 300 and m.check().ok


def test_a_summary_also_reclaims_removed_drives_and_keeps_thumbnails(tmp_path, world):
    rng, road, detour = world
    import cv2

    thumbs = [cv2.imencode(".jpg", np.full((8, 8, 3), i % 256, np.uint8))[1].tobytes()
              for i in range(300)]
    with SprintMap.create(tmp_path / "m.map", MapConfig(dim=DIM)) as m:
        m.ingest(road, name="road", thumbnails=thumbs)
        m.ingest(again(rng, road, 0.3), name="other", thumbnails=thumbs)
        m.remove_sequences(["other"])
        m.ingest(again(rng, road), name="again", thumbnails=thumbs)
        m.ingest(detour_drive(rng, road, detour), name="detour", positions=xy(300),
                 thumbnails=thumbs[::-1])
        report = m.summarize()
        assert report["vertices_before"] == 900 and report["sequences_after"] == 2
        assert m.store.removed_vertices() == 0 and m.stats()["vertices"] <= 430
        assert m.thumbnail(0, 123) == thumbs[123] and m.check().ok
        seq = m.sequence_by_name("detour")  # its image ids are its kept frames, in order
        first = int(m.positions(seq.seq_id)[0, 0])
        assert 80 <= first <= 100
        assert [m.thumbnail(seq.seq_id, i) for i in range(seq.length)] == thumbs[::-1][
            first:first + seq.length]


def test_a_map_with_nothing_repeated_is_unchanged(tmp_path, world):
    _, road, detour = world
    with SprintMap.create(tmp_path / "m.map", MapConfig(dim=DIM)) as m:
        m.ingest(road, name="road")
        m.ingest(detour, name="detour")
        edges = sorted((e.src_seq, e.src_image, e.dst_seq, e.dst_image) for e in m.edges())
        report = m.summarize()
        assert report["vertices_after"] == report["vertices_before"] == 400
        assert sorted((e.src_seq, e.src_image, e.dst_seq, e.dst_image)
                      for e in m.edges()) == edges
        assert m.check().ok


def test_bad_per_place_is_refused(everything):
    with pytest.raises(ValueError, match="per_place"):
        everything.summarize(per_place=0)


# --- a kill at any instant of summarize --------------------------------------------------------

KILL_SCRIPT = """
import sys
from sprint_map.map import SprintMap
with SprintMap.open(sys.argv[1]) as m:
    m.summarize()
"""


def logical(path: Path) -> tuple[list[tuple[str, int]], int, list[tuple[int, int, int, int]]]:
    with SprintMap.open(path, readonly=True) as m:
        report = m.check()
        assert report.ok, report.violations
        return ([(s.name, s.length) for s in m.sequences()], m.stats()["vertices"],
                sorted((e.src_seq, e.src_image, e.dst_seq, e.dst_image) for e in m.edges()))


@pytest.mark.parametrize("point", SUMMARIZE_POINTS)
def test_a_kill_leaves_the_map_as_before_or_after(everything, tmp_path, point):
    path = everything.path
    everything.close()
    before = logical(path)
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, CRASH_ENV: point, "PYTHONPATH": str(root)}
    done = subprocess.run([sys.executable, "-c", KILL_SCRIPT, str(path)], env=env, cwd=root,
                          timeout=120)
    assert done.returncode == -9
    published = point == "summarize.published"
    assert (path / CURRENT_NAME).exists() == published
    after = logical(path)
    if published:
        assert after[1] < before[1] and [n for n, _ in after[0]] == ["road", "detour"]
    else:
        assert after == before
    with SprintMap.open(path) as m:  # the writer goes on: the summary completes
        m.summarize()
        assert m.check().ok
    done_state = logical(path)
    assert [n for n, _ in done_state[0]] == ["road", "detour"]
    if published:
        assert done_state == after


READY_SCRIPT = """
import sys
from sprint_map.map import SprintMap
with SprintMap.open(sys.argv[1]) as m:
    print("ready", flush=True)
    m.summarize()
print("done", flush=True)
"""


def test_random_kills_leave_the_map_as_before_or_after(everything, tmp_path):
    """``summarize`` killed at random instants (up to 1.2 times a whole one, measured on a
    copy), 10 times: each time the map as before or as after, ``check`` passing."""
    path = everything.path
    everything.close()
    before = logical(path)
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(root)}

    def start(where: Path) -> subprocess.Popen[str]:
        child = subprocess.Popen([sys.executable, "-c", READY_SCRIPT, str(where)], env=env,
                                 cwd=root, stdout=subprocess.PIPE, text=True)
        assert child.stdout is not None and child.stdout.readline() == "ready\n"
        return child

    shutil.copytree(path, tmp_path / "copy.map")
    child = start(tmp_path / "copy.map")
    begun = time.monotonic()
    assert child.wait(timeout=120) == 0
    longest = 1.2 * (time.monotonic() - begun)
    after = logical(tmp_path / "copy.map")
    rng = np.random.default_rng(5)
    for kill in range(10):
        where = tmp_path / f"kill-{kill}.map"
        shutil.copytree(path, where)
        child = start(where)
        time.sleep(rng.uniform(0, longest))
        child.kill()
        child.wait(timeout=60)
        state = logical(where)  # check passes (in logical)
        assert state in (before, after)
        with SprintMap.open(where) as m:  # a writer's open cleans up; the map goes on
            assert m.check().ok
