"""The in-memory union-find (sprint_map/util/union_find.py) against networkx's components."""

from __future__ import annotations

import networkx as nx
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sprint_map.util.union_find import UnionFind


@settings(suppress_health_check=[HealthCheck.too_slow], deadline=None)
@given(st.integers(1, 40).flatmap(lambda n: st.tuples(
    st.just(n), st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)), max_size=60))))
def test_groups_are_the_connected_components(case: tuple[int, list[tuple[int, int]]]) -> None:
    n, pairs = case
    sets = UnionFind(n)
    graph = nx.Graph()
    graph.add_nodes_from(range(n))
    for a, b in pairs:
        sets.union(a, b)
        graph.add_edge(a, b)
    expected = sorted(sorted(c) for c in nx.connected_components(graph))
    assert sets.groups() == expected  # ascending members, ordered by the smallest
    for a, b in pairs:
        assert sets.find(a) == sets.find(b)


def test_a_set_alone_is_its_own_group() -> None:
    sets = UnionFind(3)
    sets.union(2, 2)
    assert sets.groups() == [[0], [1], [2]] and [sets.find(i) for i in range(3)] == [0, 1, 2]
