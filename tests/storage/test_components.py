"""Components: the persisted union-find agrees with the connected components of the edges."""

from __future__ import annotations

import tempfile
from pathlib import Path

import networkx as nx
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sprint_map.config import MapConfig, StoreOptions
from sprint_map.storage.check import check_map
from sprint_map.storage.records import EdgeSpec
from sprint_map.storage.store import MapStore

DIM = 2


def frames(n: int) -> np.ndarray:
    return np.arange(n * DIM, dtype=np.float32).reshape(n, DIM)


def link(*targets: int) -> list[EdgeSpec]:
    """Edges from frame 0 of the new sequence to frame 0 of each target sequence."""
    return [EdgeSpec((None, 0), (t, 0)) for t in targets]


@pytest.fixture
def store(tmp_path):
    with MapStore.create(tmp_path / "m", MapConfig(dim=DIM, store=StoreOptions(shard_rows=8))) as s:
        yield s


def components(store: MapStore) -> dict[int, list[int]]:
    return {c.component: c.sequences for c in store.components()}


def test_singletons_without_edges(store):
    for n in (1, 2, 3):
        assert store.add_sequence(frames(n)).component == store.stats()["sequences"] - 1
    assert components(store) == {0: [0], 1: [1], 2: [2]}
    assert [c.vertices for c in store.components()] == [1, 2, 3]
    assert store.stats()["components"] == 3


def test_chain(store):
    store.add_sequence(frames(2))
    for i in range(1, 6):
        result = store.add_sequence(frames(i + 1), edges=link(i - 1))
        assert result.component == 0  # ties go to the smaller id, then the larger side wins
    assert components(store) == {0: [0, 1, 2, 3, 4, 5]}
    assert store.components()[0].vertices == 2 + 2 + 3 + 4 + 5 + 6
    assert store.stats()["components"] == 1


def test_star(store):
    store.add_sequence(frames(1))
    for _ in range(5):
        store.add_sequence(frames(1), edges=[EdgeSpec((0, 0), (None, 0))])
    assert components(store) == {0: [0, 1, 2, 3, 4, 5]}
    assert all(store.component_of(s) == 0 for s in range(6))


def test_the_larger_component_keeps_its_id(store):
    store.add_sequence(frames(1))  # 0
    store.add_sequence(frames(1))  # 1
    store.add_sequence(frames(1), edges=link(1))  # 2 -> {1, 2}
    store.add_sequence(frames(1), edges=link(1))  # 3 -> {1, 2, 3}
    # 4 joins {0} first (tie: id 0 survives), then {0, 4} (2) meets {1, 2, 3} (3): 1 survives.
    assert store.add_sequence(frames(1), edges=link(0, 1)).component == 1
    assert components(store) == {1: [0, 1, 2, 3, 4]}
    assert store.component_of(0) == 1


def test_merging_already_merged_components(store):
    store.add_sequence(frames(1))  # 0
    store.add_sequence(frames(1), edges=link(0))  # 1: {0, 1}
    store.add_sequence(frames(1), edges=link(1))  # 2: {0, 1, 2}
    store.add_sequence(frames(1))  # 3
    store.add_sequence(frames(1), edges=link(3))  # 4: {3, 4}
    store.add_sequence(frames(1))  # 5
    result = store.add_sequence(frames(1), edges=link(4, 1))  # 6 bridges {3,4} and {0,1,2}
    assert result.component == 0
    assert components(store) == {0: [0, 1, 2, 3, 4, 6], 5: [5]}
    # Edges inside one component (new sequence to two members; old to old) merge nothing more.
    result = store.add_sequence(
        frames(1), edges=[*link(2, 4), EdgeSpec((0, 0), (3, 0)), EdgeSpec((3, 0), (0, 0))]
    )
    assert result.component == 0 and result.edges_added == 4
    assert components(store) == {0: [0, 1, 2, 3, 4, 6, 7], 5: [5]}
    # A new sequence may carry an edge between two old components and stay apart itself.
    result = store.add_sequence(frames(1), edges=[EdgeSpec((5, 0), (2, 0))])
    assert result.component == 8
    assert components(store) == {0: [0, 1, 2, 3, 4, 5, 6, 7], 8: [8]}
    assert store.stats()["components"] == 2
    assert check_map(store).ok


# --- property: any sequence of adds with any edges ------------------------------------------

# Per added sequence: its length, then edges as (kind, a, b, image_a, image_b) with indices taken
# modulo what exists: kind 0 = new -> old, 1 = old -> new, 2 = old -> old.
edge_strategy = st.tuples(st.integers(0, 2), st.integers(0, 10**6), st.integers(0, 10**6),
                          st.integers(0, 3), st.integers(0, 3))
add_strategy = st.tuples(st.integers(1, 4), st.lists(edge_strategy, max_size=3))


def _edge_specs(n_existing: int, length: int, raw: list[tuple[int, int, int, int, int]],
                lengths: list[int]) -> list[EdgeSpec]:
    specs = []
    for kind, a, b, image_a, image_b in raw:
        if n_existing == 0 or (kind == 2 and n_existing < 2):
            continue
        old_a, old_b = a % n_existing, b % n_existing
        if kind == 2 and old_a == old_b:
            old_b = (old_b + 1) % n_existing
        new_end = (None, image_a % length)
        end_a = (old_a, image_a % lengths[old_a])
        end_b = (old_b, image_b % lengths[old_b])
        specs.append({0: EdgeSpec(new_end, end_a), 1: EdgeSpec(end_a, new_end),
                      2: EdgeSpec(end_a, end_b)}[kind])
    return specs


def _assert_components_match(store: MapStore, graph: nx.Graph) -> None:
    want = sorted(sorted(c) for c in nx.connected_components(graph))
    got = components(store)
    assert sorted(got.values()) == want
    for root, members in got.items():
        assert root in members  # the id of a component is one of its sequences (the root)
        for seq in members:
            assert store.component_of(seq) == root
    assert store.stats()["components"] == len(want)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(add_strategy, min_size=1, max_size=12))
def test_components_equal_connected_components_of_the_edges(adds):
    graph = nx.Graph()
    lengths: list[int] = []
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m"
        with MapStore.create(path, MapConfig(dim=DIM, store=StoreOptions(shard_rows=5))) as store:
            for length, raw_edges in adds:
                specs = _edge_specs(len(lengths), length, raw_edges, lengths)
                result = store.add_sequence(frames(length), edges=specs)
                new = result.sequence.seq_id
                lengths.append(length)
                graph.add_node(new)
                for spec in specs:
                    graph.add_edge(new if spec.src[0] is None else spec.src[0],
                                   new if spec.dst[0] is None else spec.dst[0])
                assert result.component == store.component_of(new)
                _assert_components_match(store, graph)
        with MapStore.open(path, readonly=True) as store:
            _assert_components_match(store, graph)
            report = check_map(store)
            assert report.ok, report.violations
