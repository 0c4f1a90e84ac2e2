"""GeoJSON export: a valid FeatureCollection of drives and edge segments, or a clear error."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sprint_map.config import MapConfig
from sprint_map.errors import InputError
from sprint_map.map import SprintMap


def test_drives_as_lines_and_edges_as_segments(small_map, tmp_path):
    out = tmp_path / "map.geojson"
    with SprintMap.open(small_map, readonly=True) as m:
        report = m.export_geojson(out)
        pos = {s.seq_id: m.positions(s.seq_id) for s in m.sequences()}
    doc = json.loads(out.read_text())
    assert doc["type"] == "FeatureCollection" and doc["name"] == "small.map"
    for feature in doc["features"]:  # RFC 7946 structure
        assert feature["type"] == "Feature" and set(feature) == {"type", "geometry", "properties"}
        geometry = feature["geometry"]
        assert geometry["type"] in ("LineString", "Point")
        coords = geometry["coordinates"]
        points = coords if geometry["type"] == "LineString" else [coords]
        assert all(len(p) == 2 and all(isinstance(v, float) for v in p) for p in points)
        assert geometry["type"] == "Point" or len(coords) >= 2
    drives = {f["properties"]["seq_id"]: f for f in doc["features"]
              if f["properties"]["kind"] == "drive"}
    assert sorted(drives) == [0, 3, 4]  # b has no positions
    assert drives[0]["geometry"]["coordinates"] == pos[0][:, :2].tolist()
    assert drives[4]["geometry"] == {"type": "Point", "coordinates": [1.5, -2.5]}
    segments = [f for f in doc["features"] if f["properties"]["kind"] == "edge"]
    # a-c is the only edge between two placed frames; a-b (both ways) and b-c have b's end
    assert len(segments) == 1 and report.edges == 1 and report.nodes == 3
    (seg,) = segments
    assert seg["properties"] | {"prob": 0} == {"kind": "edge", "src_seq": 3, "src_image": 2,
                                               "dst_seq": 0, "dst_image": 5, "prob": 0,
                                               "added_by": 3, "frame": 2, "both_ways": False}
    assert seg["geometry"]["coordinates"] == [pos[3][2, :2].tolist(), pos[0][5, :2].tolist()]
    assert report.skipped_edges == doc["sprint_map"]["edges_without_positions"] == 3


def test_a_match_both_ways_is_drawn_once(tmp_path, rng):
    from sprint_map.storage.records import EdgeSpec

    with SprintMap.create(tmp_path / "m", MapConfig(dim=4)) as m:
        for name in ("a", "b"):
            edges = [EdgeSpec((None, 1), (0, 2), 0.8, 1), EdgeSpec((0, 2), (None, 1), 0.8, 1)]
            m.add_sequence(rng.standard_normal((4, 4)).astype(np.float32), name=name,
                           positions=rng.uniform(0, 9, (4, 2)), edges=edges if name == "b" else [])
        m.export_geojson(tmp_path / "g.json")
    segments = [f for f in json.loads((tmp_path / "g.json").read_text())["features"]
                if f["properties"]["kind"] == "edge"]
    assert len(segments) == 1 and segments[0]["properties"]["both_ways"] is True


def test_a_map_without_positions_is_a_clear_error(tmp_path, rng):
    with SprintMap.create(tmp_path / "m", MapConfig(dim=4)) as m:
        m.add_sequence(rng.standard_normal((5, 4)).astype(np.float32))
        with pytest.raises(InputError, match="no positions"):
            m.export_geojson(tmp_path / "g.json")
    assert not (tmp_path / "g.json").exists()
    assert not list(tmp_path.glob("*.partial"))
