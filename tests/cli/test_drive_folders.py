"""Several drives in one ingest, each with its own positions.csv; names from the folders
where the sources' names collide."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.errors import InputError
from sprint_map.map import SprintMap

DIM = 16


def _cli(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def drive(folder, n, seed, header="frame,x,y", rows=None):
    folder.mkdir(parents=True)
    x = np.random.default_rng(seed).standard_normal((n, DIM)).astype(np.float32)
    np.save(folder / "descriptors.npy", x / np.linalg.norm(x, axis=1, keepdims=True))
    if rows is not None:
        (folder / "positions.csv").write_text(header + "\n" + "".join(f"{r}\n" for r in rows))


def test_each_drive_folder_brings_its_positions_and_name(tmp_path):
    drive(tmp_path / "drives" / "mon", 4, 0, rows=[f"{i},{i * 10},5" for i in range(4)])
    drive(tmp_path / "drives" / "tue", 3, 1, header="frame,x,y,sigma_m",  # one frame: x, y
          rows=["0,1.5,2,2.5", "2,3,4,3"])
    drive(tmp_path / "drives" / "wed", 2, 2)  # no positions
    assert _cli("init", tmp_path / "m", "--dim", DIM).exit_code == 0
    sources = sorted((tmp_path / "drives").glob("*/descriptors.npy"))
    result = _cli("ingest", tmp_path / "m", *sources, "--no-merge", "--json")
    assert result.exit_code == 0, result.output
    assert [d["name"] for d in json.loads(result.output)] == ["mon", "tue", "wed"]
    with SprintMap.open(tmp_path / "m", readonly=True) as m:
        np.testing.assert_array_equal(m.positions(0)[:, :2], [[i * 10, 5] for i in range(4)])
        tue = m.positions(1)
        assert tue.shape == (3, 5) and np.isnan(tue[1]).all()  # frame 1: no fix
        np.testing.assert_array_equal(tue[[0, 2], 4], [2.5, 3])
        np.testing.assert_array_equal(tue[[0, 2], :2], [[1.5, 2], [3, 4]])
        assert m.geo_frame() is None
        assert m.positions(2) is None


def test_names_that_still_collide_are_one_error(tmp_path):
    drive(tmp_path / "a" / "run", 2, 0)
    drive(tmp_path / "b" / "run", 2, 1)
    assert _cli("init", tmp_path / "m", "--dim", DIM).exit_code == 0
    result = _cli("ingest", tmp_path / "m", tmp_path / "a" / "run" / "descriptors.npy",
                  tmp_path / "b" / "run" / "descriptors.npy")
    assert result.exit_code == InputError.exit_code
    assert "would all be named 'run'" in result.output and result.output.count("\n") == 1
    with SprintMap.open(tmp_path / "m", readonly=True) as m:
        assert m.stats()["sequences"] == 0


@pytest.mark.parametrize("bad", ["0,1,1,0", "0,nan,1,1", "5,1,1,1"])
def test_a_bad_positions_file_of_one_drive_stops_before_anything(tmp_path, bad):
    drive(tmp_path / "d" / "mon", 3, 0, rows=["0,1,1"])
    drive(tmp_path / "d" / "tue", 3, 1, header="frame,x,y,sigma_m", rows=[bad])
    assert _cli("init", tmp_path / "m", "--dim", DIM).exit_code == 0
    result = _cli("ingest", tmp_path / "m", *sorted((tmp_path / "d").glob("*/descriptors.npy")))
    assert result.exit_code == InputError.exit_code and "tue/positions.csv:2" in result.output
    with SprintMap.open(tmp_path / "m", readonly=True) as m:
        assert m.stats()["sequences"] == 0
