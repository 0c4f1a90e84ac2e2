"""LaggedLocalizer: lag 0 is the causal localizer, a lag as long as the drive is the smoothed
pass over the recorded hits, each frame is answered once and in order, even across a commit."""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.config import MapConfig
from sprint_map.errors import InputError
from sprint_map.localize.lagged import MAX_LAG, LaggedLocalizer
from sprint_map.map import SprintMap

DIM = 32


def unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


@pytest.fixture
def road(rng: np.random.Generator) -> np.ndarray:
    """200 places along a road; neighbours look alike."""
    cur, out = unit(rng.standard_normal(DIM)), []
    for _ in range(200):
        cur = unit(0.9 * cur + 0.44 * unit(rng.standard_normal(DIM)))
        out.append(cur)
    return np.array(out)


def noisy(rng: np.random.Generator, places: np.ndarray, noise: float = 0.6) -> np.ndarray:
    return unit(places + noise * unit(rng.standard_normal(places.shape)))


@pytest.fixture
def road_map(tmp_path, rng, road):
    path = tmp_path / "road.map"
    with SprintMap.create(path, MapConfig(dim=DIM)) as m:
        m.add_sequence(noisy(rng, road, 0.3), name="first")
    return path


def test_lag_zero_is_the_causal_localizer(road_map, rng, road):
    query = noisy(rng, road[20:120])
    with SprintMap.open(road_map, readonly=True) as m:
        causal = m.localizer().localize(query)
        assert LaggedLocalizer(m, 0).localize(query) == causal
        stepper = LaggedLocalizer(m, 0)
        assert [stepper.step(row) for row in query] == causal


def test_a_lag_as_long_as_the_drive_is_the_smoothed_pass_over_the_recorded_hits(
        road_map, rng, road):
    query = noisy(rng, road[50:110])
    with SprintMap.open(road_map, readonly=True) as m:
        recorder = m.localizer(record=True)  # keeps max(k, smooth_k) hits per frame
        recorder.localize(query)
        smoothed = recorder.smooth_pass(recorder.hits)
        assert LaggedLocalizer(m, len(query)).localize(query) == smoothed
        assert LaggedLocalizer(m, MAX_LAG).localize(query) == smoothed


@pytest.mark.parametrize("lag", [1, 5, 12])
def test_streamed_answers_come_lag_frames_late_in_order_and_equal_the_batch(
        road_map, rng, road, lag):
    query = noisy(rng, road[10:90])
    with SprintMap.open(road_map, readonly=True) as m:
        batch = LaggedLocalizer(m, lag).localize(query)
        stepper = LaggedLocalizer(m, lag)
        answers = [stepper.step(row) for row in query]
        assert answers[:lag] == [None] * lag
        assert stepper.waiting == lag
        tail = stepper.flush()
        streamed = [a for a in answers if a is not None] + tail
        assert [d.frame for d in streamed] == list(range(len(query)))
        assert streamed == batch
        assert stepper.timing.frames == len(query)
        # better than causal on this aliased road
        truth = np.arange(10, 90)
        right = [sum(d.image_id is not None and abs(d.image_id - t) <= 1
                     for d, t in zip(ds, truth, strict=True))
                 for ds in (m.localizer().localize(query), batch)]
        assert right[1] >= right[0]


def test_every_frame_is_answered_once_across_a_commit(tmp_path, rng, road):
    path = tmp_path / "live.map"
    with SprintMap.create(path, MapConfig(dim=DIM)) as m:
        m.add_sequence(noisy(rng, road, 0.3), name="first")
        query = noisy(rng, road[30:130])
        lagged = LaggedLocalizer(m, 6, record=True)
        out = [lagged.step(row) for row in query[:50]]
        m.ingest(noisy(rng, road[:150], 0.3), name="second")  # the map changes underneath
        out += [lagged.step(row) for row in query[50:]]
        out = [d for d in out if d is not None] + lagged.flush()
        assert [d.frame for d in out] == list(range(len(query)))
        assert len(lagged.localizer.hits) == len(query)
        right = sum(d.image_id is not None and abs(d.image_id - (30 + d.frame)) <= 2
                    for d in out[60:])
        assert right >= 0.6 * len(out[60:])


@pytest.mark.parametrize("lag", [-1, MAX_LAG + 1, 1.5, True])
def test_a_bad_lag_is_one_input_error(road_map, lag):
    with SprintMap.open(road_map, readonly=True) as m:
        with pytest.raises(InputError, match="lag"):
            LaggedLocalizer(m, lag)
        with pytest.raises(InputError, match="lag"):
            m.localize(np.zeros((3, DIM), np.float32), lag=lag)


def test_a_lag_cannot_be_combined_with_whole_drive_smoothing(road_map):
    with SprintMap.open(road_map, readonly=True) as m, pytest.raises(InputError, match="lag"):
        m.localize(np.zeros((3, DIM), np.float32), lag=3, smooth=True)


def test_pending_answers_as_flush_would_and_changes_nothing(road_map, road, rng):
    rows = noisy(rng, road[:40])
    with SprintMap.open(road_map, readonly=True) as m:
        whole = LaggedLocalizer(m, 6).localize(rows)
        lagged = LaggedLocalizer(m, 6)
        first = [d for d in (lagged.step(r) for r in rows[:20]) if d is not None]
        peeked = lagged.pending()
        assert [d.frame for d in peeked] == list(range(14, 20))
        assert lagged.waiting == 6 and lagged.pending() == peeked  # read twice, same
        rest = [d for d in (lagged.step(r) for r in rows[20:]) if d is not None]
        assert first + rest + lagged.flush() == whole
        cut = LaggedLocalizer(m, 6)
        for r in rows[:20]:
            cut.step(r)
        assert cut.flush() == peeked


def test_the_waiting_beliefs_are_counted_as_they_are_held(road_map, road, rng):
    """``held_bytes`` of the fixed-lag smoother follows the memory its waiting frames take
    (traced allocations of the steps), and is 0 once they are answered."""
    import tracemalloc

    rows = noisy(rng, road[:120])
    with SprintMap.open(road_map, readonly=True) as m:
        lagged = LaggedLocalizer(m, MAX_LAG)
        lagged.step(rows[0])  # components loaded, caches warm
        tracemalloc.start()
        try:
            for row in rows[1:]:
                lagged.step(row)
            traced = tracemalloc.get_traced_memory()[0]
        finally:
            tracemalloc.stop()
        held = lagged.smoother.held_bytes
        assert lagged.waiting == len(rows)
        assert 0.6 * traced <= held <= 1.5 * traced, (held, traced)
        lagged.flush()
        assert lagged.smoother.held_bytes == 0
