"""CSV export: three tables the csv module reads back, with the map's counts and values."""

from __future__ import annotations

import csv
import math

from sprint_map.export.tables import EDGE_COLUMNS, SEQUENCE_COLUMNS, VERTEX_COLUMNS
from sprint_map.map import SprintMap


def read(path):
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def test_tables_read_back_with_the_right_counts(small_map, tmp_path):
    out = tmp_path / "tables"  # made by the export
    with SprintMap.open(small_map, readonly=True) as m:
        report = m.export_csv(out)
        seqs, stats, edges = m.sequences(), m.stats(), m.edges()
        positions = {s.seq_id: m.positions(s.seq_id) for s in seqs}
        components = {s.seq_id: m.component_of(s.seq_id) for s in seqs}
    sequences, vertices, edge_rows = (read(out / f"{n}.csv")
                                      for n in ("sequences", "vertices", "edges"))
    assert list(sequences[0]) == list(SEQUENCE_COLUMNS)
    assert list(vertices[0]) == list(VERTEX_COLUMNS) and list(edge_rows[0]) == list(EDGE_COLUMNS)
    assert [(int(r["seq_id"]), r["name"], int(r["frames"]), int(r["component"]), r["source"])
            for r in sequences] == [(s.seq_id, s.name, s.length, components[s.seq_id], s.source)
                                    for s in seqs]
    assert len(vertices) == sum(s.length for s in seqs) == 48 == report.nodes
    assert len(edge_rows) == stats["edges"] == 4 == report.edges
    for row in vertices:
        pos = positions[int(row["seq_id"])]
        if pos is None:
            assert (row["x"], row["y"], row["heading"], row["timestamp"]) == ("", "", "", "")
            continue
        want = pos[int(row["image_id"])]
        for key, value in zip(("x", "y", "heading", "timestamp"), want, strict=True):
            assert row[key] == ("" if math.isnan(value) else repr(float(value)))
    assert [(int(r["src_seq"]), int(r["src_image"]), int(r["dst_seq"]), int(r["dst_image"]),
             float(r["prob"]), int(r["added_by"]), None if r["frame"] == "" else int(r["frame"]),
             float(r["time"])) for r in edge_rows] == [
        (e.src_seq, e.src_image, e.dst_seq, e.dst_image, e.prob, e.added_by, e.frame, e.time)
        for e in edges]
    assert report.files == [str(out / f"{n}.csv") for n in ("sequences", "vertices", "edges")]


def test_a_file_in_place_of_the_directory_is_refused(small_map, tmp_path):
    import pytest

    from sprint_map.errors import InputError

    (tmp_path / "f").write_text("x")
    with SprintMap.open(small_map, readonly=True) as m, pytest.raises(InputError):
        m.export_csv(tmp_path / "f")


def test_a_failure_half_way_leaves_the_old_file_and_no_temp_file(small_map, tmp_path,
                                                                 monkeypatch):
    import pytest

    from sprint_map.errors import MapCorruptError
    from sprint_map.storage.scan import MapScan

    out = tmp_path / "tables"
    with SprintMap.open(small_map, readonly=True) as m:
        m.export_csv(out)
        before = (out / "edges.csv").read_bytes()

        def broken(self):
            raise MapCorruptError("corrupt map record: a torn edge")
            yield  # a generator, like the real one

        monkeypatch.setattr(MapScan, "edges", broken)
        with pytest.raises(MapCorruptError):
            m.export_csv(out)
    assert (out / "edges.csv").read_bytes() == before
    assert sorted(p.name for p in out.iterdir()) == ["edges.csv", "sequences.csv",
                                                     "vertices.csv"]


def test_text_utf8_cannot_encode_is_replaced(tmp_path, rng):
    import numpy as np

    from sprint_map.config import MapConfig

    with SprintMap.create(tmp_path / "m", MapConfig(dim=4)) as m:
        m.add_sequence(rng.standard_normal((3, 4)).astype(np.float32), name="ok",
                       source="drive \udcff")
        m.export_csv(tmp_path / "c")
    assert read(tmp_path / "c" / "sequences.csv")[0]["source"] == "drive ?"
