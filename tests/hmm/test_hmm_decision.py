"""Place runs: the small-place path (Python sets) and the large-place path (numpy) agree;
candidates over parts laid end to end rank as over one view per part."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sprint_map.hmm import HMMConfig, MemoryGraphSource
from sprint_map.hmm.decision import (
    CANDIDATE_FLOOR,
    BeliefView,
    place_mass,
    place_runs,
    place_runs_np,
    top_candidates,
    top_positions,
)
from sprint_map.hmm.graph import ComponentGraph
from sprint_map.hmm.transition import ComponentTransition


def component_of_a_vertex(data: st.DataObject, max_seqs: int, max_edges: int
                          ) -> tuple[MemoryGraphSource, int, ComponentGraph, ComponentTransition]:
    """A drawn map of up to ``max_seqs`` sequences and ``max_edges`` edges, a drawn vertex,
    its component's graph and transition."""
    lengths = data.draw(st.lists(st.integers(1, 15), min_size=1, max_size=max_seqs))
    n = sum(lengths)
    edges = data.draw(st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1),
                                         st.just(1.0)), max_size=max_edges))
    source = MemoryGraphSource(lengths, edges)
    vertex = data.draw(st.integers(0, n - 1))
    graph = source.load_component(int(source.components_of(np.array([vertex]))[0]))
    return source, vertex, graph, ComponentTransition(graph, HMMConfig())


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_small_and_large_place_paths_give_the_same_runs(data: st.DataObject) -> None:
    source, vertex, graph, trans = component_of_a_vertex(data, 6, 25)
    rng = np.random.default_rng(data.draw(st.integers(0, 2**32 - 1)))
    x = np.zeros(trans.n_slots)
    x[trans.vertex_slots()] = rng.random(graph.n_vertices)
    view = BeliefView(graph, trans.slot_first, x)
    slot = int(trans.slots_of(np.array([vertex]))[0])
    radius = data.draw(st.integers(0, 3))
    hops = data.draw(st.integers(1, 4))
    runs = place_runs(view, slot, radius, hops)
    s = int(graph.seq_index(np.array([vertex]))[0])
    image = vertex - int(graph.seq_first[s])
    lo, hi = max(image - radius, 0), min(image + radius, int(graph.seq_len[s]) - 1)
    assert runs == place_runs_np(view, s, lo, hi, radius, hops)
    # Runs are sorted and disjoint, cover the vertex, and each vertex counts once.
    flat = [v for a, b in runs for v in range(a, b)]
    assert flat == sorted(set(flat)) and slot in flat
    assert np.isclose(place_mass(view, slot, radius, hops), x[flat].sum(), rtol=1e-12)


def test_place_contrast_compares_the_place_with_the_rest_of_the_map() -> None:
    from sprint_map.hmm.decision import place_contrast

    src = MemoryGraphSource([40, 40, 40], [(5, 45, 1.0)])  # drives 0 and 1 joined at 5 <-> 45
    graph = src.load_component(src.components_of(np.array([0]))[0])
    first = {int(s): int(f) for s, f in zip(graph.seq_ids, graph.seq_first, strict=True)}
    slot_first = np.array([0, 45], dtype=np.int64)  # two sequences of 40 + gutter 5
    view = BeliefView(graph, slot_first, np.zeros(90))
    slot = 5  # drive 0, image 5
    # a hit on the drive joined by the edge is the same place, not a rival
    assert place_contrast(view, slot, [5, first[1] + 5], [0.2, 0.1], 2, 1, 10) == 0.0
    # the same road 8 images on is the place's surroundings (reach 10), not a rival either
    assert place_contrast(view, slot, [5, 13], [0.2, 0.1], 2, 1, 10) == 0.0
    # ... but with a reach of 4 it is elsewhere
    assert place_contrast(view, slot, [5, 13], [0.2, 0.1], 2, 1, 4) == 2.0
    # a hit in another component (drive 2) is elsewhere
    assert place_contrast(view, slot, [6, 90], [0.1, 0.4], 2, 1, 10) == 0.25
    # no hit inside the place: it does not stand out at all
    assert place_contrast(view, slot, [90], [0.4], 2, 1, 10) == float("inf")
    assert place_contrast(view, slot, [], [], 2, 1, 10) == float("inf")


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_place_contrast_is_the_ratio_over_the_places_slots(data: st.DataObject) -> None:
    """The contrast read from the place's runs as vertex id ranges equals the definition: the
    best hit whose slot lies in the place over the best hit whose slot (if any) lies outside
    the place widened to ``reach``."""
    from sprint_map.hmm.decision import place_contrast

    source, vertex, graph, trans = component_of_a_vertex(data, 5, 12)
    n = source.n_vertices
    view = BeliefView(graph, trans.slot_first, np.zeros(trans.n_slots))
    slot = int(trans.slots_of(np.array([vertex]))[0])
    radius, hops = data.draw(st.integers(0, 3)), data.draw(st.integers(1, 3))
    reach = data.draw(st.integers(radius, radius + 6))
    hits = data.draw(st.lists(st.integers(0, n - 1), min_size=1, max_size=8, unique=True))
    dists = data.draw(st.lists(st.floats(0.01, 5.0), min_size=len(hits), max_size=len(hits)))
    inner = {v for a, b in place_runs(view, slot, radius, hops) for v in range(a, b)}
    outer = {v for a, b in place_runs(view, slot, reach, hops) for v in range(a, b)}
    member = source.components_of(np.array(hits)) == graph.component_id
    best_in = best_out = float("inf")
    for h, d, mine in zip(hits, dists, member.tolist(), strict=True):
        sl = int(trans.slots_of(np.array([h]))[0]) if mine else -1
        if sl in inner:
            best_in = min(best_in, d)
        elif sl not in outer:
            best_out = min(best_out, d)
    want = 0.0 if best_out == float("inf") else (
        float("inf") if best_in == float("inf") else best_in / best_out)
    assert place_contrast(view, slot, hits, dists, radius, hops, reach) == want


@settings(max_examples=200, deadline=None)
@given(st.lists(st.lists(st.sampled_from([0.0, 1e-9, 1e-5, 0.005, 0.1, 0.5, 0.7, 1.0]),
                         max_size=12), min_size=1, max_size=5), st.integers(1, 6))
def test_top_positions_rank_like_top_candidates_over_one_view_per_part(
        parts: list[list[float]], m: int) -> None:
    """Ties included: every value equal to the m-th largest is ranked, then by position."""
    laid = np.array([v for part in parts for v in part])
    got = top_positions(laid, m)
    peak = max(laid.tolist(), default=0.0)
    qualify = [(v, p) for p, v in enumerate(laid.tolist())
               if peak > 0 and v >= peak * CANDIDATE_FLOOR]
    assert got == sorted(qualify, key=lambda c: (-c[0], c[1]))[:m]
    # the same as top_candidates over one view per part where no two values tie
    distinct = laid + np.arange(laid.size) * 1e-3 * (laid > 0)
    views: list[BeliefView] = []
    at = 0
    graph = MemoryGraphSource([100]).load_component(0)
    for part in parts:
        views.append(BeliefView(graph, np.array([0]), distinct, a=at, b=at + len(part)))
        at += len(part)
    per_view = top_candidates(views, m)  # slots: positions in ``distinct``
    assert [(p, slot) for p, _, slot in per_view] == top_positions(distinct, m)
