"""``sprint-map ingest ... --ray``: a private runtime (``local``) and a cluster's address."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.helpers.fleet import NOISE, areas_of, base_map, copy_map, save_drives, snapshot
from tests.helpers.worlds import drive

pytestmark = pytest.mark.ray

CLI = [sys.executable, "-c", "from sprint_map.cli.main import main; main()"]


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, timeout=300)


@pytest.fixture
def fleet(tmp_path: Path, rng: np.random.Generator) -> tuple[Path, list[str]]:
    areas = areas_of(rng, 4)
    base = base_map(tmp_path / "base.map", areas[:2], rng)
    return base, save_drives(tmp_path / "drives",
                             [drive(areas[a], rng, NOISE) for a in (0, 2, 1, 0, 3)])


def test_ingest_with_ray_local_equals_ingest_without(tmp_path: Path,
                                                    fleet: tuple[Path, list[str]]) -> None:
    """``--ray local``: a private runtime of this machine's cores (``ray.init``); the
    cluster's address form is what tests/fleet/test_farm_faults.py runs."""
    base, sources = fleet
    serial = copy_map(base, tmp_path / "serial.map")
    farmed = copy_map(base, tmp_path / "farm.map")
    plain = run("ingest", str(serial), *sources, "--json")
    assert plain.returncode == 0, plain.stderr
    out = run("ingest", str(farmed), *sources, "--json", "--ray", "local")
    assert out.returncode == 0, out.stderr
    got = json.loads(out.stdout)
    assert [d["name"] for d in got] == [Path(s).stem for s in sources]
    want = json.loads(plain.stdout)
    assert [(d["seq_id"], d["edges_added"]) for d in got] == [
        (d["seq_id"], d["edges_added"]) for d in want]
    assert snapshot(farmed) == snapshot(serial)


def test_ray_refuses_what_the_farm_cannot_do(tmp_path: Path,
                                             fleet: tuple[Path, list[str]]) -> None:
    base, sources = fleet
    out = run("ingest", str(base), sources[0], "--trace", str(tmp_path / "t.npz"),
              "--ray", "local")
    assert out.returncode != 0 and "--trace is not available with --ray" in out.stderr
