"""The forward-backward smoother over the sparse active set against the full-graph one."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from test_hmm_equivalence import SETTINGS, configs, dense, frames, maps

from sprint_map.hmm import FullGraphFilter, HMMConfig, MemoryGraphSource, SprintFilter
from sprint_map.hmm.smoother import (
    RESCALE_ABOVE,
    RESCALE_BELOW,
    RIVAL_CONFIRMATIONS,
    RIVAL_SLACK,
    ConfirmedRivals,
    ForwardBackward,
    backward_operator,
    backward_step,
    smooth,
)


def forwarded(data: st.DataObject, max_frames: int) -> tuple[HMMConfig, ForwardBackward]:
    """A drawn map and unpruned config, and 2 .. ``max_frames`` drawn frames filtered."""
    lengths, edges = data.draw(maps())
    config = data.draw(configs(prune=0.0))
    source = MemoryGraphSource(lengths, edges)
    fb = ForwardBackward(config, source)
    for ids, dists in frames(data.draw, source.n_vertices, data.draw(st.integers(2, max_frames))):
        fb.forward(ids, dists)
    return config, fb


def sparse_posteriors(fb: ForwardBackward, n: int) -> list[tuple[np.ndarray, float]]:
    out = []
    for parts, sink in fb.posteriors():
        p = np.zeros(n)
        for trans, slots, gamma in parts:
            p[trans.vertex_of_slots(slots)] = gamma
        out.append((p, sink))
    return out


@SETTINGS
@given(data=st.data())
def test_unpruned_smoother_equals_full_graph_forward_backward(data: st.DataObject) -> None:
    lengths, edges = data.draw(maps())
    config = data.draw(configs(prune=0.0))
    source = MemoryGraphSource(lengths, edges)
    n = source.n_vertices
    hits = frames(data.draw, n, data.draw(st.integers(1, 15)))
    full = FullGraphFilter(config, source)
    expected = full.smooth(hits)
    fb = ForwardBackward(config, source)
    for ids, dists in hits:
        fb.forward(ids, dists)
    got = sparse_posteriors(fb, n)
    assert len(got) == len(expected)
    state = full.state_index(np.arange(n))
    for (p, sink), (fp, fsink) in zip(got, expected, strict=True):
        np.testing.assert_allclose(p, dense(n, np.arange(n), fp[state]), rtol=0, atol=1e-10)
        assert sink == pytest.approx(fsink, abs=1e-10)
        assert p.sum() + sink == pytest.approx(1.0, abs=1e-9)


def test_last_frame_smoothed_equals_filtered() -> None:
    source = MemoryGraphSource([30, 30])
    config = HMMConfig()
    fb = ForwardBackward(config, source)
    rng = np.random.default_rng(3)
    for t in range(12):
        fb.forward(np.array([t, 30 + int(rng.integers(30))]), np.array([0.1, 0.4]))
    filtered_parts, filtered_sink = fb.filter.live_belief()
    parts, sink = fb.posteriors()[-1]
    assert sink == pytest.approx(filtered_sink, abs=1e-12)
    for (_, s1, a), (_, s2, g) in zip(filtered_parts, parts, strict=True):
        np.testing.assert_array_equal(s1, s2)
        np.testing.assert_allclose(a, g, atol=1e-12)


def test_the_future_corrects_an_early_ambiguous_frame() -> None:
    """Two roads; the first frames' best hit is on the wrong one, later frames settle it.

    The causal filter follows the decoy at first; the smoothed decisions place every frame on
    the right road.
    """
    source = MemoryGraphSource([40, 40])
    config = HMMConfig(dist_scale=0.05)
    fb = ForwardBackward(config, source)
    causal = SprintFilter(config, source)
    causal_seq = []
    for t in range(15):
        if t < 3:  # the decoy (road 1) is a hair closer at first
            ids, dists = np.array([45 + t, 5 + t]), np.array([0.100, 0.101])
        else:  # then only road 0 is retrieved (and a scattered far hit)
            ids, dists = np.array([5 + t, 79 - 2 * t]), np.array([0.05, 0.3])
        fb.forward(ids, dists)
        causal_seq.append(causal.step(ids, dists).seq_id)
    smoothed = fb.decisions()
    assert causal_seq[0] == 1
    assert [d.seq_id for d in smoothed] == [0] * 15
    assert [d.image_id for d in smoothed][:5] == [5, 6, 7, 8, 9]


def test_smooth_function_and_empty() -> None:
    source = MemoryGraphSource([10])
    assert smooth(HMMConfig(), source, []) == []
    out = smooth(HMMConfig(), source, [(np.array([i]), np.array([0.1])) for i in range(5)])
    assert [d.image_id for d in out] == [0, 1, 2, 3, 4]


def five_drives_of_one_street(length: int = 40) -> MemoryGraphSource:
    edges = [(d * length + i, (d + 1) * length + i, 0.9)
             for d in range(4) for i in range(0, length, 2)]
    edges += [(b, a, w) for a, b, w in edges]
    return MemoryGraphSource([length] * 5, edges)


def test_smoothed_answers_stay_on_one_drive_of_a_shared_place() -> None:
    """Where five drives joined by edges show the place, the smoothed decisions report it by
    one drive frame after frame (the place and its mass do not change)."""
    source = five_drives_of_one_street()
    fb = ForwardBackward(HMMConfig(), source)
    rng = np.random.default_rng(5)
    for t in range(5, 30):
        fb.forward(np.array([d * 40 + t for d in range(5)]), 0.1 + 0.01 * rng.random(5))
    out = fb.decisions()
    assert len({d.seq_id for d in out}) == 1
    assert all(abs(d.image_id - t) <= 1 for d, t in zip(out, range(5, 30), strict=True))
    assert min(d.prob for d in out[3:]) > 0.8


def test_decide_prefers_the_named_drive_inside_the_place() -> None:
    source = five_drives_of_one_street()
    filt = SprintFilter(HMMConfig(), source)
    for t in range(5, 25):
        filt.update(np.array([d * 40 + t for d in range(5)]), np.full(5, 0.1))
    parts, sink = filt.live_belief()
    (trans, slots, probs), = parts
    from sprint_map.hmm.decision import BeliefView, decide, top_candidates

    x = np.zeros(trans.n_slots)
    x[slots] = probs
    view = BeliefView(trans.graph, trans.slot_first, x, idx=slots)
    cands = top_candidates([view], 4)
    plain = decide([view], cands, sink, 2, 4, 0.2, 1, len(slots))
    other = 3 if plain.seq_id != 3 else 1
    pref = decide([view], cands, sink, 2, 4, 0.2, 1, len(slots), prefer_seq=other)
    assert pref.seq_id == other and abs(pref.image_id - plain.image_id) <= 2
    assert pref.prob == plain.prob
    # a drive the place does not hold changes nothing
    assert decide([view], cands, sink, 2, 4, 0.2, 1, len(slots), prefer_seq=77) == plain


def test_novelty_dist_can_be_set_per_frame() -> None:
    source = MemoryGraphSource([30])
    fb = ForwardBackward(HMMConfig(), source)
    for t in range(10):
        fb.forward(np.array([t, 20]), np.array([0.5, 0.9]))
    before = fb.filter.sink_prob
    fb.set_novelty_dist(0.1)  # every hit is now farther than an unmapped place would be
    for t in range(10, 15):
        fb.forward(np.array([t, 20]), np.array([0.5, 0.9]))
    assert fb.filter.sink_prob > 0.5 > before
    fb.set_novelty_dist(None)
    with pytest.raises(ValueError):
        fb.set_novelty_dist(float("nan"))


def test_smoothed_matches_report_their_places_contrast() -> None:
    fb = ForwardBackward(HMMConfig(), MemoryGraphSource([50, 50]))
    for t in range(6):  # the drive follows drive 0; drive 1's image 20 looks half as close
        fb.forward(np.array([10 + t, 70]), np.array([0.1, 0.2]))
    decisions = fb.decisions()
    assert [d.image_id for d in decisions] == [10, 11, 12, 13, 14, 15]
    assert [d.contrast for d in decisions] == pytest.approx([0.5] * 6)
    # the causal filter does not compute it
    assert math.isnan(SprintFilter(HMMConfig(), MemoryGraphSource([50, 50])).step(
        np.array([10, 70]), np.array([0.1, 0.2])).contrast)


def test_a_rival_counts_only_if_the_frames_around_confirm_it() -> None:
    # The drive follows drive 0 (hits at 10 + t, distance 0.1). A stray near neighbour on
    # drive 1 (a different image every frame) is not a rival; a route on drive 1 that advances
    # with the drive (60 + t) is, and at the same distance the place no longer stands out.
    def run(rival_of: Callable[[int], int]) -> list[float]:
        fb = ForwardBackward(HMMConfig(), MemoryGraphSource([50, 50]))
        for t in range(8):
            fb.forward(np.array([10 + t, rival_of(t)]), np.array([0.1, 0.1]))
        return [d.contrast for d in fb.decisions()]

    stray = run(lambda t: 50 + (7 * t) % 40)
    route = run(lambda t: 60 + t)
    assert stray == pytest.approx([0.0] * 8)
    assert route[2:6] == pytest.approx([1.0] * 4)


@SETTINGS
@given(data=st.data())
def test_confirmed_rivals_are_the_hits_two_of_the_four_frames_around_confirm(
        data: st.DataObject) -> None:
    """``h in ConfirmedRivals(t, nearest)`` exactly when at least RIVAL_CONFIRMATIONS of the
    frames t - 2 .. t + 2 hold a hit within RIVAL_SLACK of h + d (the set definition)."""
    hits = st.lists(st.integers(0, 60), max_size=10)
    nearest = [(ids, [0.0] * len(ids)) for ids in data.draw(st.lists(hits, min_size=1,
                                                                     max_size=7))]
    t = data.draw(st.integers(0, len(nearest) - 1))
    rivals = ConfirmedRivals(t, nearest)
    for h in range(-5, 66):
        around = [d for d in (-2, -1, 1, 2) if 0 <= t + d < len(nearest)
                  and any(abs(w - (h + d)) <= RIVAL_SLACK for w in nearest[t + d][0])]
        assert (h in rivals) == (len(around) >= RIVAL_CONFIRMATIONS), (h, t, nearest)


@SETTINGS
@given(data=st.data())
def test_the_backward_operator_is_every_parts_operator_at_once(data: st.DataObject) -> None:
    """One application of :func:`backward_operator` over the parts laid end to end equals,
    float for float, each part's own operator (:meth:`ComponentTransition.pull_operator`,
    the next frame's likelihood ratios folded in) applied to its component's part of the next
    frame (the sink's share alone where it has none)."""
    _, fb = forwarded(data, 6)
    now, nxt = fb.frames[-2], fb.frames[-1]
    beta = np.array(data.draw(st.lists(st.floats(0, 5), min_size=nxt.starts()[-1],
                                       max_size=nxt.starts()[-1])))
    sink = data.draw(st.floats(0, 5))
    starts = nxt.starts()
    index = {trans.graph.component_id: j for j, (trans, _, _) in enumerate(nxt.parts)}
    each = []
    for trans, slots, _ in now.parts:
        j = index.get(trans.graph.component_id, -1)
        if j < 0:
            each.append(trans.pull_operator(slots, np.zeros(0, np.int64)).apply(np.zeros(0),
                                                                                sink))
            continue
        m_trans, m_slots, _ = nxt.parts[j]
        op = trans.pull_operator(slots, m_slots)
        lik = dict(zip(nxt.hit_ids, nxt.hit_lik, strict=True))
        e = np.array([lik.get(v, 1.0) for v in m_trans.vertex_of_slots(m_slots).tolist()])
        if (e != 1.0).any() and op.m_sel.size:
            op.weigh_targets(e)
        each.append(op.apply(beta[starts[j]: starts[j + 1]], sink))
    want = np.concatenate(each) if each else np.zeros(0)
    np.testing.assert_array_equal(backward_operator(now, nxt).pull.apply(beta, sink), want)


@SETTINGS
@given(data=st.data())
def test_held_hits_are_the_slots_whose_vertex_is_a_hit(data: st.DataObject) -> None:
    """:meth:`FrameBelief.held_hits`: every position of the parts laid end to end whose
    vertex is one of the frame's hits, ascending, with that hit's likelihood ratio."""
    _, fb = forwarded(data, 6)
    for frame in fb.frames:
        lik = dict(zip(frame.hit_ids, frame.hit_lik, strict=True))
        vids = [v for trans, slots, _ in frame.parts for v in trans.vertex_of_slots(slots).tolist()]
        pos, got = frame.held_hits()
        assert pos.tolist() == [p for p, v in enumerate(vids) if v in lik]
        assert got.tolist() == [lik[vids[p]] for p in pos.tolist()]


@SETTINGS
@given(data=st.data())
def test_the_backward_steps_bound_holds_every_value(data: st.DataObject) -> None:
    """``backward_step``'s third value bounds every value it returns, sink included, and the
    values are the normalised recursion's up to one factor."""
    config, fb = forwarded(data, 10)
    beta, sink, bound = np.ones(fb.frames[-1].starts()[-1]), 1.0, 1.0
    ref, ref_sink = beta.copy(), 1.0
    for t in range(len(fb.frames) - 2, -1, -1):
        now, nxt = fb.frames[t], fb.frames[t + 1]
        beta, sink, bound = backward_step(config, now, nxt, beta, sink, bound=bound)
        assert max(beta.max(initial=0.0), sink) <= bound
        ref, ref_sink, _ = backward_step(config, now, nxt, ref, ref_sink, bound=math.inf)
        top = max(beta.max(initial=0.0), sink)
        if top > 0.0:
            np.testing.assert_allclose(np.append(beta, sink) / top, np.append(ref, ref_sink),
                                       rtol=1e-9, atol=1e-300)


def test_a_long_pass_with_extreme_likelihoods_stays_in_range() -> None:
    """Likelihood ratios far from 1 for thousands of frames: the backward values are rescaled
    before they could overflow or reach subnormal floats, and the smoothed posterior is the
    same as with a rescale at every step."""
    source = MemoryGraphSource([3000])
    config = HMMConfig(dist_scale=0.01)  # hit likelihood ratios near e^90
    fb = ForwardBackward(config, source)
    rng = np.random.default_rng(0)
    for t in range(2500):
        fb.forward(np.array([t, int(rng.integers(3000))]), np.array([0.0, 0.9]))
    beta, sink, bound = np.ones(fb.frames[-1].starts()[-1]), 1.0, 1.0
    ref, ref_sink = beta.copy(), 1.0
    for t in range(len(fb.frames) - 2, -1, -1):
        now, nxt = fb.frames[t], fb.frames[t + 1]
        beta, sink, bound = backward_step(config, now, nxt, beta, sink, bound=bound,
                                          keep=True)
        ref, ref_sink, _ = backward_step(config, now, nxt, ref, ref_sink, bound=math.inf)
        values = np.append(beta, sink)
        assert np.isfinite(values).all() and values.max() <= RESCALE_ABOVE
        assert values.max() >= RESCALE_BELOW
        top = max(ref.max(initial=0.0), ref_sink)
        np.testing.assert_allclose(values / values.max(), np.append(ref, ref_sink) / top,
                                   rtol=1e-9, atol=1e-300)
