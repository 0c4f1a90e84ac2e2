"""A drive against the drives it matched: the matrix, its decisions, precision and recall."""

from __future__ import annotations

import base64

import numpy as np
import pytest

from sprint_map.map import SprintMap
from sprint_map.viewer.matrix import RADIUS_M, drive_detail, match_matrix, pair_decisions
from sprint_map.viewer.overview import MapOverview


@pytest.fixture
def summary(road_map):
    with SprintMap.open(road_map.path, readonly=True) as m:
        yield MapOverview(m)


@pytest.mark.parametrize("size", [512, 37])
def test_matrix_is_the_sampled_descriptors_distances(summary, size):
    m = summary.map
    out = match_matrix(summary, 1, 0, size=size)
    rows, cols = np.array(out["rows"]), np.array(out["cols"])
    assert len(rows) == min(size, 100) and rows[0] == 0 and rows[-1] == 99
    a, b = m.descriptors(1)[rows].astype(float), m.descriptors(0)[cols].astype(float)
    d = ((a[:, None] - b[None]) ** 2).sum(-1)
    pixels = np.frombuffer(base64.b64decode(out["pixels"]), np.uint8).reshape(len(rows), len(cols))
    # brightest where closest: the byte order follows the distance order
    assert pixels.flat[d.argmin()] == 255 and pixels.flat[d.argmax()] == 0
    assert out["dist_range"][0] == pytest.approx(d.min(), rel=1e-4)
    if size > 100:  # drives of one road: the diagonal band is brighter than the rest
        band = np.abs(rows[:, None] - cols[None]) <= 5
        assert pixels[band].mean() > pixels[~band].mean() + 50


def test_decisions_are_the_edges_between_the_drives(summary):
    m = summary.map
    edges = m.edges(1)
    out = match_matrix(summary, 1, 0)
    dec = out["decisions"]
    mine = {(e.src_image, e.dst_image) for e in edges if e.src_seq == 1 and e.dst_seq == 0}
    theirs = {(e.dst_image, e.src_image) for e in edges if e.src_seq == 0 and e.dst_seq == 1}
    assert set(zip(dec["frame"], dec["image"], strict=True)) == mine | theirs
    assert all(by for f, i, by in zip(dec["frame"], dec["image"], dec["by_self"], strict=True)
               if (f, i) in mine)  # drive 1 was merged after drive 0: its own edges
    assert len(pair_decisions(edges, 1, 2)) > 0 and len(pair_decisions(edges, 1, 3)) == 0


def test_precision_and_recall_from_positions(summary):
    m = summary.map
    out = match_matrix(summary, 1, 0)
    ps, pt = m.positions(1)[:, :2], m.positions(0)[:, :2]
    dec = out["decisions"]
    right = [np.linalg.norm(ps[f] - pt[i]) <= RADIUS_M for f, i in
             zip(dec["frame"], dec["image"], strict=True)]
    pr = out["pr"]
    assert pr["correct"] == sum(right) and pr["precision"] == pytest.approx(np.mean(right), abs=1e-4)
    has = [(np.linalg.norm(pt - p, axis=1) <= RADIUS_M).any() for p in ps]
    assert pr["frames_with_match"] == sum(has)
    good = {f for f, r in zip(dec["frame"], right, strict=True) if r}
    assert pr["recall"] == pytest.approx(len(good) / sum(has), abs=1e-4)
    assert pr["precision"] > 0.9 and pr["recall"] > 0.5


def test_drive_detail_lists_the_matched_drives(summary):
    d = drive_detail(summary, 1)
    assert d is not None and d["frames"] == 100 and d["has_positions"]
    assert {r["seq_id"] for r in d["matched"]} == {0, 2}
    assert sum(r["edges"] for r in d["matched"]) == d["edges"] == len(summary.map.edges(1))
    assert drive_detail(summary, 3)["matched"] == []  # the separate road
    assert drive_detail(summary, 99) is None
    with pytest.raises(KeyError):
        match_matrix(summary, 1, 99)
