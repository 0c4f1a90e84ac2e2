"""GraphML export: read back by networkx.read_graphml equal in vertices, edges and attributes
(on a small map, and on a 100k-vertex one: the issue's target)."""

from __future__ import annotations

import math

import networkx as nx
import numpy as np
import pytest

from sprint_map.config import MapConfig, StoreOptions
from sprint_map.errors import InputError
from sprint_map.export import graphml
from sprint_map.export.report import VERTEX_LEVEL_LIMIT, choose_level
from sprint_map.map import SprintMap
from sprint_map.storage.records import EdgeSpec

POSITION_KEYS = ("x", "y", "heading", "timestamp")


def expected_vertex_graph(m: SprintMap) -> nx.DiGraph:
    """The vertex graph from the facade's own readers (not the export's scan)."""
    graph = nx.DiGraph()
    for seq in m.sequences():
        pos = m.positions(seq.seq_id)
        for image in range(seq.length):
            data = {"seq_id": seq.seq_id, "image_id": image,
                    "component": m.component_of(seq.seq_id)}
            if pos is not None:
                data.update({k: float(v) for k, v in zip(POSITION_KEYS, pos[image], strict=True)
                             if not math.isnan(v)})
            graph.add_node(f"{seq.seq_id}:{image}", **data)
    for e in m.edges():
        data = {"prob": e.prob, "time": e.time, "added_by": e.added_by}
        if e.frame is not None:
            data["frame"] = e.frame
        graph.add_edge(f"{e.src_seq}:{e.src_image}", f"{e.dst_seq}:{e.dst_image}", **data)
    return graph


def assert_same_graph(got: nx.DiGraph, want: nx.DiGraph) -> None:
    assert dict(got.nodes(data=True)) == dict(want.nodes(data=True))
    assert {(u, v): d for u, v, d in got.edges(data=True)} == {
        (u, v): d for u, v, d in want.edges(data=True)}


@pytest.mark.parametrize("chunk", [3, graphml.CHUNK])
def test_vertex_level_reads_back_equal(small_map, tmp_path, monkeypatch, chunk):
    monkeypatch.setattr(graphml, "CHUNK", chunk)  # several chunks of nodes and of edges
    out = tmp_path / "v.graphml"
    with SprintMap.open(small_map, readonly=True) as m:
        report = m.export_graphml(out)
        want = expected_vertex_graph(m)
    assert report.level == "vertex" and (report.nodes, report.edges) == (48, 4)
    got = nx.read_graphml(out)
    assert got.is_directed()
    assert_same_graph(got, want)
    assert {k: got.graph[k] for k in ("level", "sequences", "vertices", "edges")} == {
        "level": "vertex", "sequences": 4, "vertices": 48, "edges": 4}
    assert got.nodes["3:0"]["x"] == want.nodes["3:0"]["x"] and "heading" not in got.nodes["3:0"]
    assert "x" not in got.nodes["1:0"]  # b has no positions: none written
    assert not list((tmp_path).glob("*.partial"))


def test_sequence_level_aggregates_pairs(small_map, tmp_path):
    out = tmp_path / "s.graphml"
    with SprintMap.open(small_map, readonly=True) as m:
        report = m.export_graphml(out, level="sequence")
        edges = m.edges()
    got = nx.read_graphml(out)
    assert report.level == "sequence" and got.graph["level"] == "sequence"
    assert sorted(got.nodes) == ["0", "1", "3", "4"]
    assert got.nodes["3"] == {"seq_id": 3, "name": 'c, "quoted"', "frames": 15, "component": 0,
                              "source": "drives/c/", "created": got.nodes["3"]["created"],
                              "positions": True}
    assert got.nodes["1"]["positions"] is False and got.nodes["4"]["component"] == 4
    pairs: dict[tuple[str, str], list[float]] = {}
    for e in edges:
        pairs.setdefault((str(e.src_seq), str(e.dst_seq)), []).append(e.prob)
    assert {(u, v): (d["edges"], d["prob_max"]) for u, v, d in got.edges(data=True)} == {
        k: (len(p), max(p)) for k, p in pairs.items()}
    assert got.edges["1", "3"]["added_by"] == "3"


def test_level_rule():
    assert choose_level(None, VERTEX_LEVEL_LIMIT) == "vertex"
    assert choose_level(None, VERTEX_LEVEL_LIMIT + 1) == "sequence"
    assert choose_level("vertex", 10**7) == "vertex"
    with pytest.raises(InputError):
        choose_level("frame", 10)


def test_default_level_switches_beyond_the_limit(small_map, tmp_path, monkeypatch):
    monkeypatch.setattr("sprint_map.export.report.VERTEX_LEVEL_LIMIT", 47)
    with SprintMap.open(small_map, readonly=True) as m:
        assert m.export_graphml(tmp_path / "a.graphml").level == "sequence"
        assert m.export_graphml(tmp_path / "b.graphml", "vertex").level == "vertex"


def test_a_directory_or_missing_parent_is_refused(small_map, tmp_path):
    with SprintMap.open(small_map, readonly=True) as m:
        with pytest.raises(InputError, match="is a directory"):
            m.export_graphml(tmp_path)
        with pytest.raises(InputError, match="not a directory"):
            m.export_graphml(tmp_path / "no" / "such.graphml")


VERTICES, DRIVE = 100_000, 2_000


@pytest.mark.slow
def test_100k_vertex_graphml_reads_back_equal(tmp_path):
    rng = np.random.default_rng(17)
    path = tmp_path / "big.map"
    with SprintMap.create(path, MapConfig(dim=4, store=StoreOptions(index_type="flat"))) as m:
        for seq in range(VERTICES // DRIVE):
            positions = rng.uniform(-1e4, 1e4, (DRIVE, 3)) if seq % 3 else None
            edges = [EdgeSpec((None, i), (seq - 1, i), float(rng.random()), i if i % 2 else None)
                     for i in range(0, DRIVE, 40)] if seq else []
            m.add_sequence(rng.standard_normal((DRIVE, 4)).astype(np.float32),
                           positions=positions, edges=edges)
        report = m.export_graphml(tmp_path / "big.graphml")
        want = expected_vertex_graph(m)
    assert (report.level, report.nodes, report.edges) == ("vertex", VERTICES, 49 * 50)
    got = nx.read_graphml(tmp_path / "big.graphml")
    assert got.number_of_nodes() == VERTICES and got.number_of_edges() == 49 * 50
    assert_same_graph(got, want)


def test_text_xml_cannot_hold_is_replaced(tmp_path, rng):
    with SprintMap.create(tmp_path / "m", MapConfig(dim=4)) as m:
        m.add_sequence(rng.standard_normal((3, 4)).astype(np.float32), name="ok",
                       source="cam\x01era \udcff/x")
        m.export_graphml(tmp_path / "s.graphml", "sequence")
    assert nx.read_graphml(tmp_path / "s.graphml").nodes["0"]["source"] == "cam\ufffdera \ufffd/x"
