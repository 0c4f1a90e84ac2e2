"""The overview's summary: every drive and edge accounted for, bounded sizes, both modes."""

from __future__ import annotations

import json

import numpy as np

from sprint_map.config import MapConfig
from sprint_map.map import SprintMap
from sprint_map.storage.records import EdgeSpec
from sprint_map.viewer.overview import GRID, MapOverview
from tests.helpers.road_map import DIM, build_road_map


def test_overview_draws_every_drive_on_its_positions_and_every_edge(road_map):
    with SprintMap.open(road_map.path, readonly=True) as m:
        ov = MapOverview(m).overview()
        stats, seqs = m.stats(), m.sequences()
        edges = m.edges()
        pos = {s.seq_id: m.positions(s.seq_id)[:, :2] for s in seqs}
    assert ov["mode"] == "positions"
    assert ov["counts"]["vertices"] == stats["vertices"] and ov["counts"]["disk_bytes"] > 0
    assert ov["sequences"]["id"] == [s.seq_id for s in seqs]
    assert ov["points"] == [s.length for s in seqs]  # small: nothing decimated
    # the quantised points decode back to the positions (to the grid's resolution)
    lo, span = np.array(ov["bbox"][:2]), ov["bbox"][2] - ov["bbox"][0]
    xy = np.array(ov["xy"]).reshape(-1, 2) / GRID * span + lo
    np.testing.assert_allclose(xy, np.vstack(list(pos.values())), atol=span / GRID)
    assert ov["edges"]["level"] == "vertex" and ov["edges"]["drawn"] == len(edges)
    seg = np.array(ov["edges"]["xy"]).reshape(-1, 4) / GRID * span
    first = edges[0]
    want = np.r_[pos[first.src_seq][first.src_image], pos[first.dst_seq][first.dst_image]] \
        - np.r_[lo, lo]
    np.testing.assert_allclose(seg[0], want, atol=span / GRID)
    # pairs: the road's drives chained, the separate road alone
    pairs = ov["pairs"]
    assert sum(pairs["edges"]) == len(edges) == stats["edges"]
    assert {(a, b) for a, b in zip(pairs["a"], pairs["b"], strict=True)} >= {(0, 1), (1, 2)}
    assert 3 not in pairs["a"] + pairs["b"]


def test_large_maps_are_summarised_within_the_budgets(tmp_path, rng):
    """Budgets scaled down so a small map exceeds them: points decimated per drive (both
    ends kept), edges aggregated per pair with a few segments each, the same counts."""
    lengths = [400, 120, 300, 50]
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        for i, n in enumerate(lengths):
            t = np.arange(n, dtype=float)
            edges = [EdgeSpec((None, j), (i - 1, j), 0.9) for j in range(0, min(n, lengths[i - 1]), 2)
                     ] if i else []
            m.add_sequence(rng.standard_normal((n, DIM)).astype(np.float32), name=f"d{i}",
                           positions=np.c_[t, t * 0 + i, t * 0, t], edges=edges)
    with SprintMap.open(tmp_path / "m", readonly=True) as m:
        ov = MapOverview(m, point_budget=100, edge_budget=20).overview()
        n_edges = m.stats()["edges"]
    assert ov["points"] == [max(2, int(100 * n / sum(lengths))) for n in lengths]
    xy = np.array(ov["xy"]).reshape(-1, 2)
    starts = np.r_[0, np.cumsum(ov["points"])[:-1]]
    assert (xy[starts, 0] == 0).all()  # each drive's first point kept
    assert ov["edges"]["level"] == "pair" and ov["edges"]["drawn"] == 3 * 3
    assert sum(ov["pairs"]["edges"]) == n_edges and ov["pairs"]["total"] == 3
    assert len(json.dumps(ov)) < 10_000


def test_a_map_without_positions_is_drawn_as_a_layout_of_its_sequence_graph(tmp_path, rng):
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        for i in range(4):
            edges = [EdgeSpec((None, 0), (i - 1, 0), 1.0)] if i in (1, 2) else []
            m.add_sequence(rng.standard_normal((10, DIM)).astype(np.float32), edges=edges)
    with SprintMap.open(tmp_path / "m", readonly=True) as m:
        ov = MapOverview(m).overview()
    assert ov["mode"] == "layout" and "xy" not in ov
    layout = np.array(ov["layout"]).reshape(-1, 2)
    assert layout.shape == (4, 2) and layout.min() >= 0 and layout.max() <= GRID
    assert len({tuple(p) for p in layout.tolist()}) == 4  # every drive its own node
    assert ov["sequences"]["component"][0] == ov["sequences"]["component"][2]
    assert ov["sequences"]["component"][3] != ov["sequences"]["component"][0]


def test_the_overview_is_cached_until_the_map_changes(tmp_path, rng):
    build_road_map(tmp_path / "m", rng, drives=2, frames=60)
    with SprintMap.open(tmp_path / "m") as m:
        summary = MapOverview(m)
        first = summary.overview()
        assert summary.overview() is first
        m.add_sequence(rng.standard_normal((30, DIM)).astype(np.float32), name="new")
        again = summary.overview()
    assert again is not first and again["sequences"]["name"][-1] == "new"
    assert again["sequences"]["positions"][-1] is False
