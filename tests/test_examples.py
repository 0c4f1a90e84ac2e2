"""example_map: the drives it is asked for, of seeded rows, in a folder that goes at exit."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sprint_map.config import MapConfig
from sprint_map.errors import EmptySequenceError, InputError
from sprint_map.examples import PREFIX, example_map

ROOT = Path(__file__).resolve().parents[1]


def test_it_holds_one_sequence_per_drive_in_order_appended_as_they_are():
    with example_map({"mon": 5, "tue": 3, "wed": 1}) as smap:
        assert [(s.name, s.length) for s in smap.sequences()] == [("mon", 5), ("tue", 3),
                                                                  ("wed", 1)]
        assert smap.stats() == {"sequences": 3, "vertices": 9, "edges": 0, "components": 3}
        assert smap.config.dim == 8 and not smap.readonly
        assert Path(smap.path).name.startswith(PREFIX)


@pytest.mark.parametrize("drives", [None, {}])
def test_without_drives_it_is_an_empty_map(drives):
    with example_map(drives, dim=16) as smap:
        assert smap.stats()["sequences"] == 0 and smap.config.dim == 16


def test_the_rows_are_the_draws_of_one_generator_of_the_seed():
    rng = np.random.default_rng(7)
    expected = [rng.standard_normal((n, 4)).astype(np.float32) for n in (5, 3)]
    with example_map({"mon": 5, "tue": 3}, dim=4, seed=7) as smap:
        for seq_id, rows in enumerate(expected):
            np.testing.assert_array_equal(smap.descriptors(seq_id), rows)


def test_the_same_seed_gives_the_same_rows_another_seed_others():
    def rows(seed: int) -> np.ndarray:
        with example_map({"mon": 6}, seed=seed) as smap:
            return np.array(smap.descriptors(0))

    np.testing.assert_array_equal(rows(0), rows(0))
    assert not np.array_equal(rows(0), rows(1))


def test_a_config_is_kept_and_its_dim_must_agree():
    config = MapConfig(dim=16, descriptor_params={"note": "kept"})
    with example_map({"mon": 2}, config=config) as smap:
        assert smap.config.dim == 16 and smap.config.descriptor_params == {"note": "kept"}
    with example_map(dim=16, config=config) as smap:
        assert smap.config.dim == 16
    with pytest.raises(InputError, match="dim 8 is not the config's dim 16"):
        example_map(dim=8, config=config)


@pytest.mark.parametrize("drives", [{"mon": 0}, {"mon": 2, "tue": 0}])
def test_a_drive_refused_removes_the_folder_at_once(drives, monkeypatch, tmp_path):
    monkeypatch.setenv("TMPDIR", str(tmp_path))
    monkeypatch.setattr("tempfile.tempdir", None)  # tempfile reads TMPDIR again
    with pytest.raises(EmptySequenceError):
        example_map(drives)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("close", [True, False])
def test_the_folder_is_removed_when_the_interpreter_exits(close, tmp_path):
    """Closed or still open: atexit removes it (and the folders of several maps)."""
    script = ("from sprint_map.examples import example_map\n"
              "maps = [example_map({'mon': 5}), example_map()]\n"
              "for m in maps: print(m.path)\n"
              + ("for m in maps: m.close()\n" if close else "")
              + "import os; assert all(os.path.isdir(m.path) for m in maps)\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT), "TMPDIR": str(tmp_path)}
    done = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True,
                          text=True, check=True, timeout=120)
    paths = done.stdout.split()
    assert len(paths) == 2 and all(p.startswith(str(tmp_path)) for p in paths)
    assert not any(os.path.exists(p) for p in paths)
    assert list(tmp_path.iterdir()) == []
