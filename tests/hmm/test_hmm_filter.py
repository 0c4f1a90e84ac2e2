"""Behaviour of SprintFilter: initialisation, new hypotheses, novelty, place mass, cost, errors."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from sprint_map.hmm import (
    ComponentCache,
    ComponentGraph,
    Decision,
    FullGraphFilter,
    HMMConfig,
    MemoryGraphSource,
    SprintFilter,
)

CLOSE, FAR = 0.1, 0.6


class CountingSource:
    """A GraphSource wrapper that records what the filter asks for."""

    def __init__(self, inner: MemoryGraphSource) -> None:
        self.inner = inner
        self.loaded: list[int] = []
        self.asked: list[int] = []

    def components_of(self, vertex_ids: np.ndarray) -> np.ndarray:
        self.asked.extend(np.asarray(vertex_ids).tolist())
        return self.inner.components_of(vertex_ids)

    def load_component(self, component_id: int) -> ComponentGraph:
        self.loaded.append(component_id)
        return self.inner.load_component(component_id)


def hits(*pairs: tuple[int, float]) -> tuple[np.ndarray, np.ndarray]:
    return (np.array([p[0] for p in pairs], dtype=np.int64),
            np.array([p[1] for p in pairs], dtype=np.float32))


def drive(filt: SprintFilter, true_vertices: list[int], decoys: list[int]) -> list[Decision]:
    """Frames whose best hit is the true vertex, plus far decoys."""
    out = []
    for v, decoy in zip(true_vertices, decoys, strict=True):
        out.append(filt.step(*hits((v, CLOSE), (decoy, FAR))))
    return out


@pytest.fixture
def four_roads() -> MemoryGraphSource:
    """Four unconnected sequences of 60 images (vertex ids 0-59, 60-119, ...)."""
    return MemoryGraphSource([60, 60, 60, 60])


def test_initialisation_uses_the_first_frame_hits_only(four_roads: MemoryGraphSource) -> None:
    source = CountingSource(four_roads)
    filt = SprintFilter(HMMConfig(), source)
    assert filt.sink_prob == 1.0 and filt.n_active_components == 0
    decision = filt.step(*hits((5, CLOSE), (7, FAR)))
    assert filt.n_active_components == 1
    assert source.loaded == [0]
    vids, probs, sink = filt.posterior()
    assert set(vids[probs > 0].tolist()) == {5, 7}
    assert probs[vids == 5][0] > probs[vids == 7][0]
    # Nothing propagated yet; the live support is the hits (5 and 7, one window: they are
    # closer than W - 1); the component has 60 vertices.
    assert decision.n_active_vertices == 0
    assert filt.n_live_vertices == 3 and filt.n_component_vertices == 60
    assert probs.sum() + sink == pytest.approx(1.0)


def test_follows_a_sequence_and_beats_a_lone_decoy(four_roads: MemoryGraphSource) -> None:
    filt = SprintFilter(HMMConfig(), four_roads)
    rng = np.random.default_rng(0)
    path = list(range(10, 40))
    # Every third frame the retrieval ranks a random decoy first: the filter must not follow it.
    out = []
    for t, v in enumerate(path):
        decoy = int(rng.integers(60, 240))
        if t % 3 == 2:
            out.append(filt.step(*hits((decoy, CLOSE), (v, FAR - 0.3))))
        else:
            out.append(filt.step(*hits((v, CLOSE), (decoy, FAR))))
    settled = out[5:]
    assert all(d.vertex_id is not None and abs(d.vertex_id - v) <= 1
               for d, v in zip(settled, path[5:], strict=True))
    assert all(d.seq_id == 0 for d in settled)


@pytest.mark.parametrize("jump_to", [70, 130, 200])
def test_hits_start_new_hypotheses_after_a_jump(four_roads: MemoryGraphSource,
                                               jump_to: int) -> None:
    """The query turns onto another road: the old belief must not trap the filter."""
    filt = SprintFilter(HMMConfig(), four_roads)
    drive(filt, list(range(10, 30)), [150] * 20)
    assert filt.decide().seq_id == 0
    # From now on the retrieval returns only the true vertex (no hit on road 0 any more).
    after = [filt.step(*hits((v, CLOSE))) for v in range(jump_to, jump_to + 30)]
    recovered = [i for i, d in enumerate(after) if d.vertex_id is not None
                 and abs(d.vertex_id - (jump_to + i)) <= 1]
    assert recovered and recovered[0] <= 5
    assert all(i in recovered for i in range(recovered[0], 30))
    # The abandoned road leaves the active set once its share falls below the threshold (a
    # single hit per frame is weak evidence, e**miss_margin, so this takes a while).
    assert 0 not in filt.active_component_ids


def test_recovers_after_a_gap_of_garbage_hits(four_roads: MemoryGraphSource) -> None:
    rng = np.random.default_rng(1)
    filt = SprintFilter(HMMConfig(), four_roads)
    drive(filt, list(range(0, 15)), [100] * 15)
    # 15 frames of garbage: random hits all over the map, all about equally far.
    for _ in range(15):
        garbage = rng.integers(0, 240, size=5)
        filt.step(garbage, rng.uniform(0.55, 0.6, size=5))
    after = drive(filt, list(range(135, 155)), [10] * 20)
    good = [d.vertex_id is not None and abs(d.vertex_id - (135 + i)) <= 1
            for i, d in enumerate(after)]
    assert all(good[5:])


def test_a_filter_without_restart_mass_never_recovers(four_roads: MemoryGraphSource) -> None:
    """Why restart_prob exists: with it at 0, a hit outside the support cannot take over."""
    filt = SprintFilter(HMMConfig(restart_prob=0.0, new_place_prob=0.0), four_roads)
    drive(filt, list(range(10, 30)), [150] * 20)
    after = drive(filt, list(range(130, 145)), [20] * 15)
    assert not any(d.seq_id == 2 for d in after)


def test_mass_running_off_a_sequence_goes_to_the_sink() -> None:
    source = MemoryGraphSource([5])
    config = HMMConfig(window=(0.0, 1.0), restart_prob=0.0, new_place_prob=0.0,
                       prune_threshold=0.0)
    filt = SprintFilter(config, source)
    filt.update(*hits((4, CLOSE)))
    assert filt.sink_prob == 0.0
    # No information: the belief at the last image moves one ahead, i.e. off the end.
    filt.update(*hits((-1, 0.0)))
    assert filt.sink_prob == pytest.approx(1.0)
    assert filt.decide().vertex_id is None


def test_padding_and_duplicates_are_handled(four_roads: MemoryGraphSource) -> None:
    a = SprintFilter(HMMConfig(), four_roads)
    b = SprintFilter(HMMConfig(), four_roads)
    a.step(np.array([3, -1, 9, 3, -1]), np.array([0.2, 9.0, 0.5, 0.1, np.inf]))
    b.step(np.array([3, 9]), np.array([0.1, 0.5]))
    va, pa, sa = a.posterior()
    vb, pb, sb = b.posterior()
    np.testing.assert_array_equal(va, vb)
    np.testing.assert_allclose(pa, pb)
    assert sa == pytest.approx(sb)
    # (1, k) rows as FAISS returns them are accepted too.
    c = SprintFilter(HMMConfig(), four_roads)
    c.step(np.array([[3, 9]]), np.array([[0.1, 0.5]]))
    np.testing.assert_allclose(c.posterior()[1], pb)


def test_frames_without_hits_carry_no_information(four_roads: MemoryGraphSource) -> None:
    filt = SprintFilter(HMMConfig(), four_roads)
    decision = filt.step(*hits((-1, 0.0), (-1, 0.0)))
    assert decision.vertex_id is None and decision.sink_prob == 1.0
    assert filt.n_active_components == 0
    filt.step(np.empty(0, dtype=np.int64), np.empty(0))
    assert filt.n_active_components == 0


@pytest.mark.parametrize(("ids", "dists"), [
    (np.array([1, 2]), np.array([0.1])),                   # shape mismatch
    (np.array([[1, 2], [3, 4]]), np.zeros((2, 2))),        # a batch, not one frame
    (np.array([-2]), np.array([0.1])),                     # only -1 pads
    (np.array([1.5]), np.array([0.1])),                    # not integers
    (np.array([1, 2]), np.array([0.1, np.nan])),           # non-finite distance of a hit
    (np.array([240]), np.array([0.1])),                    # not a vertex of the map
])
def test_bad_hits_raise_and_leave_the_state_intact(four_roads: MemoryGraphSource,
                                                   ids: np.ndarray, dists: np.ndarray) -> None:
    filt = SprintFilter(HMMConfig(), four_roads)
    filt.step(*hits((5, CLOSE), (70, FAR)))
    before = filt.posterior()
    with pytest.raises(ValueError):
        filt.step(ids, dists)
    after = filt.posterior()
    np.testing.assert_array_equal(before[0], after[0])
    np.testing.assert_array_equal(before[1], after[1])
    assert before[2] == after[2]


def test_a_source_naming_the_wrong_component_is_refused(four_roads: MemoryGraphSource) -> None:
    class Liar(CountingSource):
        def components_of(self, vertex_ids: np.ndarray) -> np.ndarray:
            return np.zeros(len(vertex_ids), dtype=np.int64)   # always road 0

    filt = SprintFilter(HMMConfig(), Liar(four_roads))
    with pytest.raises(ValueError):
        filt.step(*hits((130, CLOSE)))
    assert filt.n_active_components == 0 and filt.sink_prob == 1.0   # rolled back
    filt.step(*hits((5, CLOSE)))
    before = filt.posterior()
    with pytest.raises(ValueError):
        filt.step(*hits((6, CLOSE), (130, FAR)))
    after = filt.posterior()
    assert filt.active_component_ids == [0]
    np.testing.assert_array_equal(before[1], after[1])


def test_reset_forgets_the_belief(four_roads: MemoryGraphSource) -> None:
    filt = SprintFilter(HMMConfig(), four_roads)
    drive(filt, list(range(10, 20)), [100] * 10)
    filt.reset()
    assert filt.n_active_components == 0 and filt.sink_prob == 1.0 and filt.frames == 0
    filt.step(*hits((130, CLOSE)))
    assert filt.active_component_ids == [2]


def test_place_mass_counts_every_drive_of_the_place() -> None:
    """Five drives of one street, joined by edges: the belief splits, the place does not."""
    n_drives, length = 5, 40
    edges = [(d * length + i, (d + 1) * length + i, 0.9)
             for d in range(n_drives - 1) for i in range(0, length, 2)]
    edges += [(b, a, w) for a, b, w in edges]
    source = MemoryGraphSource([length] * n_drives, edges)
    filt = SprintFilter(HMMConfig(), source)
    for t in range(5, 25):
        ids = np.array([d * length + t for d in range(n_drives)])
        decision = filt.step(ids, np.full(n_drives, CLOSE))
    assert decision.vertex_id is not None
    assert decision.image_id is not None and abs(decision.image_id - 24) <= 1
    assert decision.vertex_prob < 0.5
    assert decision.prob > 0.8
    assert decision.prob >= decision.vertex_prob
    # Without the edges, each drive is its own component and the place is one drive.
    lone = SprintFilter(HMMConfig(), MemoryGraphSource([length] * n_drives))
    for t in range(5, 25):
        lone_decision = lone.step(np.array([d * length + t for d in range(n_drives)]),
                                  np.full(n_drives, CLOSE))
    assert lone_decision.prob < 0.5 and lone_decision.vertex_id is None


def test_place_beats_a_more_probable_single_vertex() -> None:
    """A strong lone vertex vs a place split over four drives: the place wins."""
    length = 30
    edges = [(d * length + i, e * length + i, 1.0) for d in range(4) for e in range(4)
             if d != e for i in range(length)]
    source = MemoryGraphSource([length] * 4 + [length], edges)
    filt = SprintFilter(HMMConfig(place_radius=1, decision_candidates=8, dist_scale=0.05),
                        source)
    filt.update(np.array([0 * length + 10, 1 * length + 10, 2 * length + 10, 3 * length + 10,
                          4 * length + 20]), np.array([CLOSE] * 4 + [CLOSE - 0.01]))
    vids, probs, _ = filt.posterior()
    lone = probs[vids == 4 * length + 20][0]
    assert lone > probs[vids < 4 * length].max()
    decision = filt.decide()
    assert decision.candidate_id is not None and decision.candidate_id < 4 * length
    assert decision.prob > lone


@pytest.mark.parametrize("seed", [3, 4])
def test_novel_places_are_answered_no_match(seed: int) -> None:
    """Hits that never agree with each other over time: the map does not know the place."""
    rng = np.random.default_rng(seed)
    filt = SprintFilter(HMMConfig(), MemoryGraphSource([60] * 20))
    drive(filt, list(range(0, 20)), [200] * 20)
    assert filt.decide().vertex_id is not None
    answers = []
    for _ in range(40):
        ids = rng.choice(1200, size=10, replace=False)
        answers.append(filt.step(ids, np.sort(rng.uniform(0.5, 0.6, size=10))))
    no_match = [d.vertex_id is None for d in answers[5:]]
    assert np.mean(no_match) >= 0.8
    assert all(0.0 <= d.prob <= 1.0 and 0.0 <= d.sink_prob <= 1.0 for d in answers)


def test_novelty_dist_flags_far_frames(four_roads: MemoryGraphSource) -> None:
    config = HMMConfig(novelty_dist=0.3)
    filt = SprintFilter(config, four_roads)
    drive(filt, list(range(0, 10)), [200] * 10)
    assert filt.decide().vertex_id is not None
    # The same consistent track, but every hit is now farther than novelty_dist.
    for v in range(10, 16):
        decision = filt.step(*hits((v, 0.5), (200, 0.55)))
    assert decision.vertex_id is None and decision.sink_prob > 0.5


def test_decision_fields(four_roads: MemoryGraphSource) -> None:
    filt = SprintFilter(HMMConfig(), four_roads)
    decisions = drive(filt, list(range(65, 80)), [10] * 15)
    d = decisions[-1]
    assert d.is_match and d.vertex_id == 60 + d.image_id and d.seq_id == 1
    assert d.candidate_id == d.vertex_id
    assert 0.0 <= d.vertex_prob <= d.prob <= 1.0
    assert d.n_active_components == filt.n_active_components
    assert d.n_active_vertices == filt.n_active_vertices
    empty = SprintFilter(HMMConfig(), four_roads).decide()
    assert not empty.is_match and empty.candidate_id is None and empty.sink_prob == 1.0


def test_step_cost_follows_the_active_set_not_the_map() -> None:
    """A 10M-vertex map: a step allocates O(active) memory and loads only hit components."""
    big = CountingSource(MemoryGraphSource([100] * 100_000))
    filt = SprintFilter(HMMConfig(), big)
    ids = np.array([500_000, 3_000_000], dtype=np.int64)
    dists = np.array([0.1, 0.4])
    filt.step(ids, dists)
    tracemalloc.start()
    try:
        for t in range(1, 20):
            filt.step(ids + t, dists)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 200_000  # bytes; one dense belief over the map would be 80 MB
    assert sorted(set(big.loaded)) == [5000, 30000]
    # Only the live windows around the two tracks are propagated, not the two components.
    assert 0 < filt.n_active_vertices <= 60
    assert filt.n_component_vertices == 200


def test_cache_avoids_reloading_components(four_roads: MemoryGraphSource) -> None:
    source = CountingSource(four_roads)
    cache = ComponentCache(budget_bytes=1 << 20)
    filt = SprintFilter(HMMConfig(), source, cache)
    for _ in range(3):
        drive(filt, list(range(0, 20)), [100] * 20)      # road 0, decoys on road 1
        drive(filt, list(range(130, 150)), [200] * 20)   # road 2: roads 0, 1 leave the set
    assert source.loaded.count(0) == 1 and source.loaded.count(2) == 1
    assert cache.hits > 0
    # With no budget nothing is kept: every re-activation reloads.
    source2 = CountingSource(four_roads)
    filt2 = SprintFilter(HMMConfig(), source2, ComponentCache(budget_bytes=0))
    for _ in range(3):
        drive(filt2, list(range(0, 20)), [100] * 20)
        drive(filt2, list(range(130, 150)), [200] * 20)
    assert source2.loaded.count(0) == 3


def test_invalidate_remaps_the_belief_after_a_merge() -> None:
    before = MemoryGraphSource([30, 30, 30])
    # A fixed T (the adaptive rule's value here, 0.5 * (FAR - CLOSE)): the fresh filter below
    # then has the same observation model as one that saw every frame.
    exact = HMMConfig(prune_threshold=0.0, support_threshold=0.0, dist_scale=0.25)
    filt = SprintFilter(exact, before)
    drive(filt, list(range(0, 10)), [40] * 10)
    vids, probs, sink = filt.posterior()
    assert sorted(filt.active_component_ids) == [0, 1]
    # The map grows: an edge now joins sequences 0 and 1 (and 2 stays alone).
    filt.source = after = MemoryGraphSource([30, 30, 30], [(5, 35, 0.9)])
    filt.invalidate([0, 1])
    assert filt.active_component_ids == [0]
    vids2, probs2, sink2 = filt.posterior()
    keep = np.isin(vids2, vids)
    np.testing.assert_allclose(probs2[keep], probs)
    assert sink2 == sink
    # It then runs exactly like a filter that always knew the merged map.
    fresh = FullGraphFilter(exact, after)
    fresh.set_posterior(vids2, probs2, sink2)
    for t in range(10, 15):
        filt.update(*hits((t, CLOSE), (40, FAR)))
        fresh.update(*hits((t, CLOSE), (40, FAR)))
    np.testing.assert_allclose(filt.posterior()[1], fresh.posterior()[1][:60], atol=1e-12)


def test_config_must_be_an_hmm_config(four_roads: MemoryGraphSource) -> None:
    with pytest.raises(ValueError):
        SprintFilter({"k": 10}, four_roads)  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        FullGraphFilter(HMMConfig(), [])


def test_the_beam_bounds_the_active_set() -> None:
    """Forty unmerged drives whose hits scatter: at most max_active_components stay active,
    and the road the frames follow is among them."""
    source = MemoryGraphSource([50] * 40)
    rng = np.random.default_rng(11)
    for cap in (0, 6):
        filt = SprintFilter(HMMConfig(max_active_components=cap), source)
        most = 0
        for t in range(40):
            decoys = rng.choice(np.arange(50, 2000), 9, replace=False)
            ids = np.r_[t + 5, decoys]
            decision = filt.step(ids, np.r_[0.05, np.full(9, 0.3)])
            most = max(most, filt.n_active_components)
        assert decision.seq_id == 0 and abs(decision.image_id - 44) <= 1
        assert (most <= 6) if cap else (most > 6)
