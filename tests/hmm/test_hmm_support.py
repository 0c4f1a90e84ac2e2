"""Live support windows: the set operations, the trimming bound, and a step that does not grow
with the component it runs in."""

from __future__ import annotations

import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sprint_map.hmm import FullGraphFilter, HMMConfig, MemoryGraphSource, SprintFilter
from sprint_map.hmm.support import insert_sorted, merge, ranges, runs, trim

SETTINGS = settings(max_examples=150, deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

sorted_slots = st.lists(st.integers(0, 200), min_size=1, max_size=40, unique=True).map(sorted)


def window_slots(lo: np.ndarray, hi: np.ndarray) -> set[int]:
    return {s for a, b in zip(lo.tolist(), hi.tolist(), strict=True) for s in range(a, b)}


@SETTINGS
@given(st.lists(st.tuples(st.integers(-50, 50), st.integers(0, 6)), max_size=12))
def test_ranges_concatenates_aranges(spans: list[tuple[int, int]]) -> None:
    starts = np.array([s for s, _ in spans], dtype=np.int64)
    lengths = np.array([n for _, n in spans], dtype=np.int64)
    want = [v for s, n in spans for v in range(s, s + n)]
    assert ranges(starts, lengths).tolist() == want


@SETTINGS
@given(sorted_slots, st.lists(st.integers(0, 250), max_size=12))
def test_insert_sorted_is_the_sorted_union(idx: list[int], extra: list[int]) -> None:
    got = insert_sorted(np.array(idx, dtype=np.int64), np.array(extra, dtype=np.int64))
    assert got.tolist() == sorted(set(idx) | set(extra))


@SETTINGS
@given(st.lists(st.tuples(st.integers(0, 100), st.integers(1, 8)), min_size=1, max_size=12),
       st.integers(1, 5))
def test_merge_keeps_the_slots_and_separates_windows_by_the_gap(
        spans: list[tuple[int, int]], gap: int) -> None:
    lo = np.array([a for a, _ in spans], dtype=np.int64)
    hi = lo + np.array([n for _, n in spans], dtype=np.int64)
    mlo, mhi = merge(lo, hi, gap)
    assert window_slots(lo, hi) <= window_slots(mlo, mhi)
    assert np.all(mlo < mhi) and np.all(mlo[1:] >= mhi[:-1] + gap)
    # Merging only fills holes shorter than the gap: every added slot lies between two windows.
    for s in window_slots(mlo, mhi) - window_slots(lo, hi):
        assert lo.min() < s < hi.max()


@SETTINGS
@given(sorted_slots, st.integers(1, 5))
def test_runs_break_where_the_gap_is_exceeded(slots: list[int], gap: int) -> None:
    arr = np.array(slots, dtype=np.int64)
    lo, hi, first, last = runs(arr, gap)
    assert arr[first].tolist() == lo.tolist() and (arr[last] + 1).tolist() == hi.tolist()
    assert window_slots(lo, hi) >= set(slots)
    assert np.all(lo[1:] - hi[:-1] >= gap)


@SETTINGS
@given(st.data())
def test_trim_zeroes_only_negligible_slots_and_reports_their_mass(data: st.DataObject) -> None:
    n = 120
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    spans = data.draw(st.lists(st.tuples(st.integers(0, n - 10), st.integers(1, 9)),
                               min_size=1, max_size=6))
    lo, hi = merge(np.array([a for a, _ in spans], dtype=np.int64),
                   np.array([a + b for a, b in spans], dtype=np.int64), 3)
    x = np.zeros(n + 10)
    live = sorted(window_slots(lo, hi))
    x[live] = rng.exponential(size=len(live)) * rng.choice([1e-9, 1.0], size=len(live))
    before = x.copy()
    limit = data.draw(st.sampled_from([0.0, 1e-6, 0.5]))
    new_lo, new_hi, kept, trimmed = trim(x, lo, hi, limit, 3)
    assert trimmed == pytest.approx(before.sum() - x.sum(), abs=1e-12)
    # Every slot at or above the limit survives, with its value; cut slots are below it.
    assert np.all(x[before >= limit] == before[before >= limit]) if limit > 0 else True
    assert np.all(before[(before != x)] < max(limit, 1e-300))
    assert set(np.flatnonzero(x).tolist()) <= window_slots(new_lo, new_hi)
    assert set(kept.tolist()) <= window_slots(new_lo, new_hi)


def configs(prune: float, support: float) -> st.SearchStrategy[HMMConfig]:
    return st.builds(
        HMMConfig,
        window=st.sampled_from([(1.0,), (0.3, 0.5, 0.2), (0.25, 0.5, 0.15, 0.07, 0.03)]),
        edge_weight=st.sampled_from([0.0, 1.0, 3.0]),
        prune_threshold=st.just(prune),
        support_threshold=st.just(support),
        restart_prob=st.sampled_from([0.0, 0.01, 0.2]),
        new_place_prob=st.sampled_from([0.0, 0.01]),
    )


def dense(n: int, vids: np.ndarray, probs: np.ndarray) -> np.ndarray:
    out = np.zeros(n)
    out[vids] = probs
    return out


@SETTINGS
@given(st.data())
@pytest.mark.parametrize("prune", [0.0, 1e-2])
def test_trimmed_step_differs_by_at_most_the_dropped_mass(prune: float,
                                                          data: st.DataObject) -> None:
    """One step from the same prior: ||p_sprint - p_full||_1 <= 2 (pruned + trimmed mass)."""
    lengths = data.draw(st.lists(st.integers(1, 30), min_size=1, max_size=5))
    n = sum(lengths)
    edges = data.draw(st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1),
                                         st.just(1.0)), max_size=8))
    config = data.draw(configs(prune, data.draw(st.sampled_from([1e-6, 1e-3, 5e-2]))))
    source = MemoryGraphSource(lengths, edges)
    sprint = SprintFilter(config, source)
    full = FullGraphFilter(config, source)
    for t in range(data.draw(st.integers(1, 40))):
        k = data.draw(st.integers(0, 4))
        ids = np.array(data.draw(st.lists(st.integers(0, n - 1), min_size=k, max_size=k)),
                       dtype=np.int64)
        dists = np.array(data.draw(st.lists(st.floats(0.0, 2.0), min_size=k, max_size=k)))
        if t:
            full.set_posterior(*sprint.posterior())
        sprint.update(ids, dists)
        full.update(ids, dists)
        vids, probs, sink = sprint.posterior()
        diff = np.abs(dense(n, vids, probs) - full.posterior()[1]).sum() + abs(
            sink - full.sink_prob)
        assert diff <= 2 * (sprint.last_pruned_mass + sprint.last_trimmed_mass) + 1e-9
        assert probs.sum() + sink == pytest.approx(1.0, abs=1e-12)


def test_trimming_bound_is_exercised() -> None:
    """The bound above is not vacuous: trimming drops mass and the posteriors then differ."""
    source = MemoryGraphSource([200])
    config = HMMConfig(support_threshold=1e-3, prune_threshold=0.0)
    sprint = SprintFilter(config, source)
    full = FullGraphFilter(config, source)
    trimmed_steps = 0
    for t in range(40):
        ids, dists = np.array([t, 150 - t]), np.array([0.1, 0.9])
        if t:
            full.set_posterior(*sprint.posterior())
        sprint.update(ids, dists)
        full.update(ids, dists)
        diff = np.abs(dense(200, *sprint.posterior()[:2]) - full.posterior()[1]).sum()
        if sprint.last_trimmed_mass > 0:
            trimmed_steps += 1
            assert diff > 0
        assert diff <= 2 * sprint.last_trimmed_mass + 1e-12
    assert trimmed_steps > 0


def chain_map(n_seq: int, length: int) -> MemoryGraphSource:
    """``n_seq`` drives of the same route, consecutive ones joined by an edge every 10 images
    (both ways): one component, as a lifelong map becomes."""
    edges = [(a * length + i, (a + 1) * length + i, 1.0) for a in range(n_seq - 1)
             for i in range(0, length, 10)]
    edges += [(d, s, w) for s, d, w in edges]
    return MemoryGraphSource([length] * n_seq, edges)


def run_track(source: MemoryGraphSource, frames: int) -> tuple[int, float]:
    """Follow drive 0 with hits on it and on a few of the other drives; the mean propagated
    slots per frame and the wall time."""
    filt = SprintFilter(HMMConfig(), source)
    n_seq = source.n_vertices // 1000
    rng = np.random.default_rng(3)
    live = []
    start = time.perf_counter()
    for t in range(frames):
        others = rng.choice(np.arange(1, n_seq), size=min(4, n_seq - 1), replace=False)
        ids = np.r_[t, others * 1000 + t].astype(np.int64)
        filt.step(ids, np.r_[0.1, np.full(len(others), 0.3)])
        live.append(filt.n_active_vertices)
    return int(np.mean(live[frames // 2:])), time.perf_counter() - start


def test_step_follows_the_live_support_not_the_component() -> None:
    """In one ever-growing component (every drive linked to the next), the slots a step
    propagates stay about the same from 10 to 200 drives (the whole component: 20x more)."""
    small, _ = run_track(chain_map(10, 1000), 200)
    large, _ = run_track(chain_map(200, 1000), 200)
    assert small > 0 and large <= 2 * small + 50
    assert large < 200_000 / 50  # a tiny share of the component


@pytest.mark.parametrize("window", [(1.0,), (0.5, 0.5)])
def test_a_window_at_the_end_of_one_sequence_never_leaks_into_the_next(
        window: tuple[float, ...]) -> None:
    """Belief at the last image of a sequence and at the next sequence's first stays apart.

    With ``W = 1`` a layout without gutter put the two slots side by side; their windows merged
    into one spanning both sequences and the end clip sent the second one's mass to the sink.
    """
    lengths = [8, 30, 13, 1]
    source = MemoryGraphSource(lengths, [(8, 51, 1.0)])  # seqs 1 and 3 form one component
    config = HMMConfig(window=window, edge_weight=0.0, prune_threshold=0.0,
                       support_threshold=1e-6, restart_prob=0.0, new_place_prob=0.0)
    sprint = SprintFilter(config, source)
    full = FullGraphFilter(config, source)
    hits = np.array([37, 51], dtype=np.int64)
    sprint.update(hits, np.zeros(2))
    full.update(hits, np.zeros(2))
    for _ in range(3):
        sprint.update(np.empty(0, dtype=np.int64), np.empty(0))
        full.update(np.empty(0, dtype=np.int64), np.empty(0))
        vids, probs, sink = sprint.posterior()
        assert np.abs(dense(sum(lengths), vids, probs) - full.posterior()[1]).sum() < 1e-12
        assert sink == pytest.approx(full.sink_prob, abs=1e-12)
