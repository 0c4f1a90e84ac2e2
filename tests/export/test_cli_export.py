"""``sprint-map export``: the three formats in one call, --json, errors as one line."""

from __future__ import annotations

import json

import networkx as nx
import numpy as np
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.errors import InputError


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_export_all_formats(small_map, tmp_path):
    result = run("export", small_map, "--graphml", tmp_path / "g.graphml", "--csv",
                 tmp_path / "csv", "--geojson", tmp_path / "m.geojson", "--json")
    assert result.exit_code == 0, result.output
    reports = json.loads(result.output)
    assert [(r["format"], r["level"], r["nodes"], r["edges"]) for r in reports] == [
        ("graphml", "vertex", 48, 4), ("csv", None, 48, 4), ("geojson", None, 3, 1)]
    assert nx.read_graphml(tmp_path / "g.graphml").number_of_nodes() == 48
    result = run("export", small_map, "--graphml", tmp_path / "s.graphml", "--level", "sequence")
    assert result.exit_code == 0, result.output
    assert "sequence level" in result.output and "4 nodes" in result.output


def test_export_errors_are_one_line(tmp_path, rng):
    path = tmp_path / "m.map"
    assert run("init", path, "--dim", 4).exit_code == 0
    np.save(tmp_path / "a.npy", rng.standard_normal((5, 4)).astype(np.float32))
    assert run("ingest", path, tmp_path / "a.npy", "-q").exit_code == 0
    for args, words in ((["--geojson", tmp_path / "g.json"], "no positions"),
                        ([], "nothing to export"),
                        (["--csv", tmp_path / "c", "--level", "vertex"], "--level")):
        result = run("export", path, *args)
        assert result.exit_code == InputError.exit_code, result.output
        assert result.output.startswith("Error: ") and words in result.output
        assert "Traceback" not in result.output
    assert run("export", tmp_path / "nomap", "--csv", tmp_path / "c").exit_code == 3
