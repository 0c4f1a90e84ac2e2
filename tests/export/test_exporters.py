"""Every export passes the one contract (:class:`tests.helpers.contracts.ExporterContract`):
GraphML at the vertex and the sequence level, CSV and GeoJSON."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import networkx as nx

from sprint_map.export.report import ExportReport
from sprint_map.map import SprintMap
from tests.helpers.contracts import ExporterContract


def graphml_counts(report: ExportReport) -> tuple[int, int]:
    graph = nx.read_graphml(report.path)
    return graph.number_of_nodes(), graph.number_of_edges()


class TestVertexGraphML(ExporterContract):
    writer = "write_vertex_graphml"

    def target(self, tmp_path: Path) -> Path:
        return tmp_path / "map.graphml"

    def export(self, smap: SprintMap, target: Path) -> ExportReport:
        return smap.export_graphml(target, level="vertex")

    def read(self, report: ExportReport) -> tuple[int, int]:
        return graphml_counts(report)


class TestSequenceGraphML(TestVertexGraphML):
    writer = "write_sequence_graphml"

    def export(self, smap: SprintMap, target: Path) -> ExportReport:
        return smap.export_graphml(target, level="sequence")


class TestCSV(ExporterContract):
    writer = "write_table"

    def target(self, tmp_path: Path) -> Path:
        return tmp_path / "tables"

    def bad_target(self, tmp_path: Path) -> Path:
        (tmp_path / "a-file").write_text("")  # a file where a directory is due
        return tmp_path / "a-file"

    def export(self, smap: SprintMap, target: Path) -> ExportReport:
        return smap.export_csv(target)

    def read(self, report: ExportReport) -> tuple[int, int]:
        rows = {}
        for name in ("vertices.csv", "edges.csv"):
            with open(Path(report.path) / name, newline="", encoding="utf-8") as f:
                rows[name] = sum(1 for _ in csv.reader(f)) - 1  # the header
        return rows["vertices.csv"], rows["edges.csv"]


class TestGeoJSON(ExporterContract):
    writer = "write_geojson"

    def target(self, tmp_path: Path) -> Path:
        return tmp_path / "map.geojson"

    def export(self, smap: SprintMap, target: Path) -> ExportReport:
        return smap.export_geojson(target)

    def read(self, report: ExportReport) -> tuple[int, int]:
        kinds = [f["properties"]["kind"]
                 for f in json.loads(Path(report.path).read_text())["features"]]
        return kinds.count("drive"), kinds.count("edge")

