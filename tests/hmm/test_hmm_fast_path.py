"""The one-hit fast path of ``SprintFilter.update`` against its general path, and the general
path's array injection of many hits against its hit-by-hit loop, float for float."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sprint_map.hmm import HMMConfig, MemoryGraphSource, SprintFilter, sprint_filter
from sprint_map.hmm.active_set import ActiveSet
from tests.hmm.test_hmm_equivalence import configs, maps


class GeneralOnly(SprintFilter):
    """A filter whose every frame takes the general path (the reference)."""

    def update(self, hit_ids: np.ndarray, hit_dists: np.ndarray) -> None:
        vids, _, liks, sink_lik, _ = self._obs.evaluate(hit_ids, hit_dists)
        self._update_any(vids, liks, sink_lik)


@st.composite
def drives(draw: st.DrawFn, n_vertices: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Mostly one hit moving forward (the fast path), with jumps, misses and multi-hit frames."""
    out = []
    v = draw(st.integers(0, n_vertices - 1))
    for _ in range(draw(st.integers(1, 60))):
        kind = draw(st.sampled_from(["next", "next", "next", "stay", "jump", "none", "many"]))
        if kind == "next":
            v = (v + 1) % n_vertices
        elif kind == "jump":
            v = draw(st.integers(0, n_vertices - 1))
        if kind == "none":
            out.append((np.zeros(0, dtype=np.int64), np.zeros(0)))
        elif kind == "many":
            ids = [v, draw(st.integers(0, n_vertices - 1))]
            out.append((np.array(ids, dtype=np.int64), np.array([0.1, 0.4])))
        else:
            out.append((np.array([v], dtype=np.int64),
                        np.array([draw(st.sampled_from([0.0, 0.2, 1.5]))])))
    return out


def state(f: SprintFilter) -> tuple[object, ...]:
    vids, probs, sink = f.posterior()
    return (vids.tolist(), probs.tolist(), sink, f.n_active_vertices, f.active_component_ids,
            f.pruned_mass, f.trimmed_mass, f.last_pruned_mass, f.last_trimmed_mass)


@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=st.data())
def test_fast_path_gives_the_same_floats_as_the_general_path(data: st.DataObject) -> None:
    lengths, edges = data.draw(maps())
    prune = data.draw(st.sampled_from([0.0, 1e-4, 0.05]))
    support = data.draw(st.sampled_from([0.0, 1e-9, 1e-3]))
    config = data.draw(configs(prune, support))
    source = MemoryGraphSource(lengths, edges)
    fast, general = SprintFilter(config, source), GeneralOnly(config, source)
    for ids, dists in data.draw(drives(sum(lengths))):
        fast.update(ids, dists)
        general.update(ids, dists)
        assert state(fast) == state(general)


def test_fast_path_is_taken_on_a_long_drive() -> None:
    """The usual frame (one hit on the road) never reaches the general path."""
    calls = []

    class Counting(SprintFilter):
        def _update_any(self, vids: list[int], liks: list[float], sink_lik: float) -> None:
            calls.append(len(vids))
            super()._update_any(vids, liks, sink_lik)

    f = Counting(HMMConfig(), MemoryGraphSource([500, 500]))
    for v in range(400):
        f.update(np.array([v]), np.array([0.0]))
    assert calls == [1]  # the first frame (initialisation) only
    assert f.step(np.array([400]), np.array([0.0])).vertex_id == 400


@st.composite
def deep_drives(draw: st.DrawFn, n_vertices: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Frames of many distinct hits (a deep search): along the drive, and anywhere."""
    out = []
    v = draw(st.integers(0, n_vertices - 1))
    for _ in range(draw(st.integers(1, 25))):
        v = (v + draw(st.integers(0, 3))) % n_vertices
        n = draw(st.integers(0, min(24, n_vertices)))
        ids = np.unique(np.array([v] + draw(st.lists(st.integers(0, n_vertices - 1),
                                                     min_size=n, max_size=n)), dtype=np.int64))
        dists = np.array(draw(st.lists(st.sampled_from([0.0, 0.1, 0.3, 1.0, 2.5]),
                                       min_size=ids.size, max_size=ids.size)))
        out.append((ids, dists))
    return out


@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=st.data())
def test_many_hits_injected_at_once_give_the_same_floats(data: st.DataObject) -> None:
    lengths, edges = data.draw(maps())
    prune = data.draw(st.sampled_from([0.0, 1e-4, 0.05]))
    config = data.draw(configs(prune, data.draw(st.sampled_from([0.0, 1e-9, 1e-3]))))
    source = MemoryGraphSource(lengths, edges)
    arrays, loop = SprintFilter(config, source), SprintFilter(config, source)
    for ids, dists in data.draw(deep_drives(sum(lengths))):
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(sprint_filter, "MANY_HITS", 1)
            arrays.update(ids, dists)
            patch.setattr(sprint_filter, "MANY_HITS", 10**9)
            loop.update(ids, dists)
        assert state(arrays) == state(loop)


@settings(max_examples=100, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=st.data())
def test_locate_many_and_each_agree_with_locate(data: st.DataObject) -> None:
    lengths, edges = data.draw(maps())
    f = SprintFilter(HMMConfig(), MemoryGraphSource(lengths, edges))
    n = sum(lengths)
    for _ in range(data.draw(st.integers(1, 4))):  # a few frames: components come and go
        f.update(np.array([data.draw(st.integers(0, n - 1))]), np.array([0.1]))
    active = f._active  # noqa: SLF001 (the filter's own index, read by its test)
    ids = np.array(data.draw(st.lists(st.integers(0, n - 1), max_size=12, unique=True)),
                   dtype=np.int64)
    one = [active.locate(int(v)) for v in ids]
    assert active.locate_each(ids) == one
    many = active.locate_many(ids)
    if any(found is None for found in one):
        assert many is None
        return
    assert many is not None
    got = {}
    for comp, slots, at in many:
        assert np.all(np.diff(at) > 0)
        for slot, i in zip(slots.tolist(), at.tolist(), strict=True):
            got[i] = (comp, slot)
    assert got == dict(enumerate(one))


@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=st.data())
def test_components_the_beam_drops_at_once_are_never_activated_same_floats(
        data: st.DataObject) -> None:
    """A frame's hits in components the beam drops at its end anyway leave only their mass
    (:data:`sprint_filter.BEAM_AHEAD`): the same state, float for float, as activating them,
    whether the hits are located one by one or in one search."""
    lengths, edges = data.draw(maps())
    prune = data.draw(st.sampled_from([0.0, 1e-4, 0.05]))
    config = dataclasses.replace(
        data.draw(configs(prune, data.draw(st.sampled_from([0.0, 1e-9, 1e-3])))),
        max_active_components=data.draw(st.integers(0, 4)))
    source = MemoryGraphSource(lengths, edges)
    ahead, every = SprintFilter(config, source), SprintFilter(config, source)
    many = data.draw(st.sampled_from([1, 10**9]))
    for ids, dists in data.draw(deep_drives(sum(lengths))):
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(sprint_filter, "MANY_HITS", many)
            ahead.update(ids, dists)
            patch.setattr(sprint_filter, "BEAM_AHEAD", False)
            every.update(ids, dists)
        assert state(ahead) == state(every)


def test_the_beam_leaves_components_out_on_deep_frames(monkeypatch) -> None:
    """Hits spread over twelve one-drive components with a beam of 2: most of the components
    a frame meets are never activated, and the belief is the same as activating them."""
    config = HMMConfig(max_active_components=2)
    ahead = SprintFilter(config, MemoryGraphSource([30] * 12))
    every = SprintFilter(config, MemoryGraphSource([30] * 12))
    added = {id(ahead): 0, id(every): 0}
    real_add = ActiveSet.add

    def add(self, trans):
        added[id(ahead) if self is ahead._active else id(every)] += 1  # noqa: SLF001
        return real_add(self, trans)

    monkeypatch.setattr(ActiveSet, "add", add)
    rng = np.random.default_rng(3)
    for t in range(20):
        ids = np.unique(np.concatenate(([t], rng.integers(0, 360, 30))))
        dists = rng.uniform(0.0, 2.0, ids.size)
        dists[ids == t] = 0.0
        ahead.update(ids, dists)
        monkeypatch.setattr(sprint_filter, "BEAM_AHEAD", False)
        every.update(ids, dists)
        monkeypatch.setattr(sprint_filter, "BEAM_AHEAD", True)
        assert state(ahead) == state(every)
    assert added[id(every)] > 100  # (each frame meets nearly all twelve)
    assert added[id(ahead)] < added[id(every)] / 3
