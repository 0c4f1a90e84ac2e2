"""The fixed-lag smoother against the causal filter (lag 0), the whole-drive smoother (lag at
least the drive's length) and the smoother of the drive cut at t + lag (every lag)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from test_hmm_equivalence import SETTINGS, configs, frames, maps

from sprint_map.hmm import HMMConfig, MemoryGraphSource, SprintFilter, smoother
from sprint_map.hmm.fixed_lag import MAX_LAG, FixedLagSmoother, check_lag
from sprint_map.hmm.smoother import ForwardBackward
from sprint_map.hmm.transition import ComponentTransition


def lagged(config: HMMConfig, source: MemoryGraphSource, hits, lag: int) -> list:
    fl = FixedLagSmoother(config, source, lag=lag)
    out = []
    for t, (ids, dists) in enumerate(hits):
        answer = fl.push(ids, dists)
        if t < lag:
            assert answer is None
        else:
            assert answer is not None
            out.append(answer)
        assert fl.waiting == min(t + 1, lag)  # memory: never more than lag frames kept
    assert fl.answered == len(out)
    out += fl.flush()
    assert fl.waiting == 0 and fl.answered == len(hits)
    return out


def smoothed(config: HMMConfig, source: MemoryGraphSource, hits) -> list:
    fb = ForwardBackward(config, source)
    for ids, dists in hits:
        fb.forward(ids, dists)
    return fb.decisions()


@SETTINGS
@given(data=st.data())
def test_a_lag_as_long_as_the_drive_is_the_smoothed_pass(data: st.DataObject) -> None:
    lengths, edges = data.draw(maps())
    config = data.draw(configs(prune=data.draw(st.sampled_from([0.0, 0.01])),
                               support=data.draw(st.sampled_from([0.0, 1e-4]))))
    source = MemoryGraphSource(lengths, edges)
    n = data.draw(st.integers(1, 14))
    hits = frames(data.draw, source.n_vertices, n)
    lag = data.draw(st.integers(n, n + 3))
    assert lagged(config, source, hits, lag) == smoothed(config, source, hits)


@SETTINGS
@given(data=st.data())
def test_lag_zero_is_the_causal_filter(data: st.DataObject) -> None:
    lengths, edges = data.draw(maps())
    config = data.draw(configs(prune=0.01, support=1e-4))
    source = MemoryGraphSource(lengths, edges)
    hits = frames(data.draw, source.n_vertices, data.draw(st.integers(1, 14)))
    causal = SprintFilter(config, source)
    assert lagged(config, source, hits, 0) == [causal.step(ids, d) for ids, d in hits]


@SETTINGS
@given(data=st.data())
def test_each_answer_is_the_smoothed_decision_of_the_drive_cut_at_t_plus_lag(
        data: st.DataObject) -> None:
    """Frame t's answer is that of the smoother over frames 0 .. t + lag, up to the drive it
    is reported on: without edges a place never reaches another drive, so that preference
    (the previous answer's drive here, the next one's there) can only break a tie between
    equally probable vertices of the place."""
    lengths, _ = data.draw(maps())
    config = data.draw(configs(prune=0.0))
    source = MemoryGraphSource(lengths, [])
    n = data.draw(st.integers(2, 12))
    hits = frames(data.draw, source.n_vertices, n)
    lag = data.draw(st.integers(1, n - 1))
    got = lagged(config, source, hits, lag)
    for t in range(n - lag):
        want = smoothed(config, source, hits[:t + lag + 1])[t]
        if got[t].candidate_id == want.candidate_id:
            assert got[t] == want, t
        else:  # a tie: the same place, mass and sink, an equally probable vertex
            assert (got[t].prob, got[t].vertex_prob, got[t].sink_prob, got[t].is_match) == (
                want.prob, want.vertex_prob, want.sink_prob, want.is_match), t


def test_the_future_corrects_a_frame_within_the_lag() -> None:
    """Two roads; the first frames' best hit is on the decoy. The causal filter follows the
    decoy; with a lag of 5 the first frames are already placed on the right road."""
    source = MemoryGraphSource([40, 40])
    config = HMMConfig(dist_scale=0.05)
    fl, causal = FixedLagSmoother(config, source, lag=5), SprintFilter(config, source)
    answers, first = [], []
    for t in range(15):
        if t < 3:
            ids, dists = np.array([45 + t, 5 + t]), np.array([0.100, 0.101])
        else:
            ids, dists = np.array([5 + t, 79 - 2 * t]), np.array([0.05, 0.3])
        first.append(causal.step(ids, dists).seq_id)
        if (d := fl.push(ids, dists)) is not None:
            answers.append(d)
    assert first[:3] == [1, 1, 1]
    assert [d.seq_id for d in answers[:3]] == [0, 0, 0]
    assert [d.image_id for d in answers] == list(range(5, 15))


@SETTINGS
@given(data=st.data())
def test_the_pull_operator_is_the_pull(data: st.DataObject) -> None:
    lengths, edges = data.draw(maps())
    config = data.draw(configs(prune=0.0))
    graph = MemoryGraphSource(lengths, edges)
    comp = graph.components_of(np.array([0]))[0]
    trans = ComponentTransition(graph.load_component(int(comp)), config)
    slots = np.unique(trans.slots_of(np.arange(sum(lengths))
                                     [graph.components_of(np.arange(sum(lengths))) == comp]))
    pick = data.draw(st.lists(st.sampled_from(slots.tolist()), unique=True))
    src = np.sort(np.array(pick, dtype=np.int64))
    dst = np.sort(np.array(data.draw(st.lists(st.sampled_from(slots.tolist()), unique=True)),
                           dtype=np.int64))
    op = trans.pull_operator(src, dst)
    for _ in range(2):  # (the operator keeps its layout between applications)
        m = np.array(data.draw(st.lists(st.floats(0, 5), min_size=len(dst),
                                        max_size=len(dst))))
        sink = data.draw(st.floats(0, 5))
        np.testing.assert_allclose(op.apply(m, sink), trans.pull(src, dst, m, sink),
                                   rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("lag", [-1, MAX_LAG + 1, 2.0, True, "3", None])
def test_a_bad_lag_is_refused(lag) -> None:
    with pytest.raises(ValueError, match="lag"):
        check_lag(lag)
    with pytest.raises(ValueError, match="lag"):
        FixedLagSmoother(HMMConfig(), MemoryGraphSource([5]), lag=lag)


def test_every_push_builds_one_operator_so_the_first_answer_costs_no_more(monkeypatch) -> None:
    """The backward operator onto a frame is built when the next frame is pushed: the push
    that gives the first answer builds one, like every other (not ``lag`` of them)."""
    built: list[int] = []
    real = smoother.parts_pull_operator

    def counting(sources, targets, **spaces):
        built.append(1)
        return real(sources, targets, **spaces)

    monkeypatch.setattr(smoother, "parts_pull_operator", counting)
    fl = FixedLagSmoother(HMMConfig(), MemoryGraphSource([50]), lag=5)
    per_push = []
    for t in range(12):
        built.clear()
        fl.push(np.array([10 + t]), np.array([0.1]))
        per_push.append(len(built))
    assert per_push == [0] + [1] * 11
