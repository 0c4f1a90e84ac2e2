"""HMMConfig, ComponentGraph, MemoryGraphSource, ComponentCache and the transition operator."""

from __future__ import annotations

import dataclasses
import json

import networkx as nx
import numpy as np
import pytest

from sprint_map.errors import ConfigError
from sprint_map.hmm import ComponentCache, ComponentGraph, HMMConfig, MemoryGraphSource
from sprint_map.hmm.support import merge
from sprint_map.hmm.transition import ComponentTransition, full_transition_matrix

# ---------------------------------------------------------------------------------- config


def test_config_defaults_round_trip_through_json() -> None:
    config = HMMConfig()
    again = HMMConfig.from_dict(json.loads(json.dumps(config.to_dict())))
    assert again == config
    changed = HMMConfig(dist_scale=0.05, novelty_dist=0.4, window=(1.0, 2.0))
    assert HMMConfig.from_dict(json.loads(json.dumps(changed.to_dict()))) == changed
    assert changed.window == (1.0, 2.0) and changed.window_len == 2
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.k = 3  # type: ignore[misc]


@pytest.mark.parametrize("bad", [
    {"k": 0}, {"window": ()}, {"window": (0.0, 0.0)}, {"window": (-0.1, 1.0)},
    {"window": (float("nan"),)}, {"edge_weight": -1.0}, {"prune_threshold": 1.0},
    {"prune_threshold": -0.1}, {"restart_prob": 1.5}, {"restart_prob": 0.6, "new_place_prob": 0.4},
    {"dist_scale": 0.0}, {"dist_scale": float("inf")}, {"dist_scale_ema": 0.0},
    {"dist_scale_factor": 0.0}, {"miss_margin": -1.0}, {"novelty_dist": -0.5},
    {"place_radius": -1}, {"place_hops": -1}, {"decision_candidates": 0},
    {"min_confidence": 1.5}, {"cache_budget_bytes": -1}, {"k": True}, {"miss_margin": "1"},
])
def test_config_rejects_bad_values(bad: dict[str, object]) -> None:
    with pytest.raises(ValueError):
        HMMConfig(**bad)  # type: ignore[arg-type]
    with pytest.raises(ConfigError):
        HMMConfig.from_dict({**HMMConfig().to_dict(), **bad})


# ---------------------------------------------------------------------------------- graph


def test_component_graph_indexing() -> None:
    graph = ComponentGraph(7, seq_ids=[2, 5, 9], seq_first=[100, 10, 40], seq_len=[3, 4, 2],
                           edge_src=[101, 41], edge_dst=[12, 100], edge_weight=[0.5, 1.0])
    assert graph.n_vertices == 9 and graph.n_sequences == 3 and graph.n_edges == 2
    np.testing.assert_array_equal(graph.local_first, [0, 3, 7])
    np.testing.assert_array_equal(graph.vertex_ids(), [100, 101, 102, 10, 11, 12, 13, 40, 41])
    local = graph.local_index(graph.vertex_ids())
    np.testing.assert_array_equal(local, np.arange(9))
    np.testing.assert_array_equal(graph.seq_index([99, 100, 13, 14, 41, 42]), [-1, 0, 1, -1, 2, -1])
    np.testing.assert_array_equal(graph.edge_src_local, [1, 8])
    np.testing.assert_array_equal(graph.edge_dst_local, [5, 0])
    # Undirected adjacency: 1-5 and 8-0.
    adj = {v: set(graph.adj_indices[graph.adj_indptr[v]: graph.adj_indptr[v + 1]].tolist())
           for v in range(9)}
    assert adj[1] == {5} and adj[5] == {1} and adj[0] == {8} and adj[8] == {0} and adj[3] == set()
    assert graph.nbytes > 0
    with pytest.raises(ValueError):
        graph.local_index([14])


@pytest.mark.parametrize("kwargs", [
    {"seq_ids": [], "seq_first": [], "seq_len": []},
    {"seq_ids": [1, 1], "seq_first": [0, 5], "seq_len": [5, 5]},
    {"seq_ids": [2, 1], "seq_first": [0, 5], "seq_len": [5, 5]},
    {"seq_ids": [1, 2], "seq_first": [0, 4], "seq_len": [5, 5]},       # overlapping ranges
    {"seq_ids": [1], "seq_first": [0], "seq_len": [0]},
    {"seq_ids": [1], "seq_first": [-1], "seq_len": [3]},
    {"seq_ids": [1], "seq_first": [[0]], "seq_len": [[3]]},            # not one-dimensional
    {"seq_ids": [1], "seq_first": [0, 1], "seq_len": [3]},
    {"edge_src": [0], "edge_dst": [99], "edge_weight": [1.0]},            # end outside
    {"edge_src": [0], "edge_dst": [1], "edge_weight": [-1.0]},
    {"edge_src": [0], "edge_dst": [1], "edge_weight": [np.nan]},
    {"edge_src": [0, 1], "edge_dst": [1], "edge_weight": [1.0]},
])
def test_component_graph_rejects_inconsistent_arrays(kwargs: dict[str, object]) -> None:
    base: dict[str, object] = {"seq_ids": [1], "seq_first": [0], "seq_len": [5], "edge_src": [],
                               "edge_dst": [], "edge_weight": []}
    base.update(kwargs)
    with pytest.raises(ValueError):
        ComponentGraph(0, **base)  # type: ignore[arg-type]


@pytest.mark.parametrize("seed", range(5))
def test_memory_source_components_match_networkx(seed: int) -> None:
    rng = np.random.default_rng(seed)
    lengths = rng.integers(1, 6, size=12).tolist()
    n = sum(lengths)
    edges = [(int(rng.integers(n)), int(rng.integers(n)), 0.5) for _ in range(6)]
    source = MemoryGraphSource(lengths, edges)
    first = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    seq_of = np.repeat(np.arange(len(lengths)), lengths)
    g = nx.Graph()
    g.add_nodes_from(range(len(lengths)))
    g.add_edges_from((int(seq_of[a]), int(seq_of[b])) for a, b, _ in edges)
    expected = {frozenset(c) for c in nx.connected_components(g)}
    got = {frozenset(source.load_component(c).seq_ids.tolist()) for c in source.component_ids}
    assert got == expected
    comps = source.components_of(np.arange(n))
    for cid in source.component_ids:
        graph = source.load_component(cid)
        assert cid == min(graph.seq_ids.tolist())
        np.testing.assert_array_equal(np.sort(graph.vertex_ids()), np.flatnonzero(comps == cid))
        np.testing.assert_array_equal(graph.seq_first, first[graph.seq_ids])
        assert len(graph.edge_src) == sum(1 for a, _, _ in edges if comps[a] == cid)
    # One id at a time (the filter's usual call) agrees with the vectorised lookup.
    assert [source.components_of(np.array([v])).tolist() for v in range(n)] == \
        [[c] for c in comps.tolist()]
    for bad in ([n], [-1], [0, n]):
        with pytest.raises(ValueError):
            source.components_of(np.array(bad))
    with pytest.raises(ValueError):
        source.load_component(10_000)


@pytest.mark.parametrize(("lengths", "edges"), [
    ([], []), ([3, 0], []), ([3], [(0, 3, 1.0)]), ([3], [(0, 1, -0.5)]),
])
def test_memory_source_rejects_bad_input(lengths: list[int],
                                         edges: list[tuple[int, int, float]]) -> None:
    with pytest.raises(ValueError):
        MemoryGraphSource(lengths, edges)


# ---------------------------------------------------------------------------------- cache


def _graph(cid: int, length: int = 10) -> ComponentGraph:
    return ComponentGraph(cid, seq_ids=[cid], seq_first=[cid * 1000], seq_len=[length],
                          edge_src=[], edge_dst=[], edge_weight=[])


def test_cache_is_lru_within_its_budget() -> None:
    size = _graph(0).nbytes
    cache = ComponentCache(budget_bytes=3 * size)
    loads: list[int] = []

    def loader(cid: int) -> ComponentGraph:
        loads.append(cid)
        return _graph(cid)

    for cid in (1, 2, 3):
        cache.get(cid, loader)
    cache.get(1, loader)                  # 1 becomes the most recent
    cache.get(4, loader)                  # evicts 2, the least recent
    assert 2 not in cache and 1 in cache and 3 in cache and 4 in cache
    assert cache.nbytes <= cache.budget_bytes and len(cache) == 3
    cache.get(2, loader)                  # reloaded; evicts 3
    assert loads == [1, 2, 3, 4, 2] and 3 not in cache
    assert cache.hits == 1 and cache.misses == 5
    cache.invalidate([4, 99])
    assert 4 not in cache and len(cache) == 2
    cache.clear()
    assert len(cache) == 0 and cache.nbytes == 0


def test_cache_serves_but_does_not_keep_an_oversized_component() -> None:
    cache = ComponentCache(budget_bytes=100)
    graph = cache.get(5, lambda cid: _graph(cid, length=1000))
    assert graph.component_id == 5 and 5 not in cache and cache.nbytes == 0
    with pytest.raises(ValueError):
        cache.get(6, lambda cid: _graph(7))
    with pytest.raises(ValueError):
        ComponentCache(budget_bytes=-1)


# ---------------------------------------------------------------------------------- transition


@pytest.mark.parametrize("window", [(1.0,), (0.2, 0.8), (0.25, 0.5, 0.15, 0.07, 0.03),
                                    (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)])
def test_component_transition_matches_the_sparse_matrix(window: tuple[float, ...]) -> None:
    rng = np.random.default_rng(len(window))
    source = MemoryGraphSource([4, 1, 7, 3], [(0, 6, 0.8), (6, 12, 0.3), (2, 5, 1.0), (12, 1, 0.5),
                                                 (4, 13, 0.6)])
    config = HMMConfig(window=window, edge_weight=2.0)
    (graph,) = source.all_components()
    trans = ComponentTransition(graph, config)
    matrix = full_transition_matrix([graph], config, [0])
    x = rng.random(graph.n_vertices)
    slots = trans.vertex_slots()
    y = np.zeros(trans.n_slots)
    y[slots] = x
    # Every sequence is live: one window per sequence (merged where the gap allows, W = 1).
    lo, hi = merge(trans.slot_first.copy(), trans.seq_end.copy(), trans.gap)
    lo, hi, overflow, mass, n_prop = trans.propagate_windows(y, lo, hi)
    expected = matrix @ np.append(x, 0.0)
    np.testing.assert_allclose(y[slots], expected[:-1], atol=1e-15)
    assert overflow == pytest.approx(expected[-1], abs=1e-15)
    gutters = np.setdiff1d(np.arange(trans.n_slots), slots)
    assert np.all(y[gutters] == 0.0)
    assert n_prop == graph.n_vertices
    # Rows are stochastic: propagation keeps the mass (times 1 - eps - nu).
    scale = 1 - config.restart_prob - config.new_place_prob
    assert mass == pytest.approx(y.sum()) and mass + overflow == pytest.approx(scale * x.sum())
    np.testing.assert_allclose(np.asarray(matrix.sum(axis=0)).ravel(), scale)
