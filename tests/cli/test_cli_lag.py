"""``sprint-map localize --lag L``: one answer per frame in frame order, as the facade gives
them; a bad lag or one combined with --smooth/--trace is one ``Error:`` line."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.config import MapConfig
from sprint_map.errors import InputError
from sprint_map.map import SprintMap

DIM = 24


@pytest.fixture
def drive_files(tmp_path, rng):
    places = rng.standard_normal((120, DIM))

    def noisy() -> np.ndarray:
        x = places + 0.4 * rng.standard_normal(places.shape)
        return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)

    path = tmp_path / "m.map"
    with SprintMap.create(path, MapConfig(dim=DIM)) as m:
        m.add_sequence(noisy(), name="first")
    query = tmp_path / "q.npy"
    np.save(query, noisy()[10:90])
    return path, query


def test_localize_lag_answers_every_frame_in_order(drive_files):
    path, query = drive_files
    result = CliRunner().invoke(main, ["localize", str(path), str(query), "--lag", "7",
                                       "--json"])
    assert result.exit_code == 0, result.output
    got = json.loads(result.output)["decisions"]
    assert [d["frame"] for d in got] == list(range(80))
    with SprintMap.open(path, readonly=True) as m:
        want, _ = m.localize(np.load(query), lag=7)
        causal, _ = m.localize(np.load(query))
    assert got == [d.to_dict() for d in want]
    assert got != [d.to_dict() for d in causal]  # the lag changed the answers


@pytest.mark.parametrize("extra", [["--lag", "-1"], ["--lag", "10001"],
                                   ["--lag", "3", "--smooth"],
                                   ["--lag", "3", "--trace", "t.npz"]])
def test_a_bad_lag_is_one_error_line(drive_files, extra):
    path, query = drive_files
    result = CliRunner().invoke(main, ["localize", str(path), str(query), *extra])
    assert result.exit_code == InputError.exit_code
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error:") and "lag" in lines[0]
