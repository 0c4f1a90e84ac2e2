"""A map of precomputed descriptors needs no OpenCV: ``import sprint_map``, the facade and the
CLI's init / ingest / localize / info / check of ``.npy`` drives all run with ``cv2`` blocked.

Each case runs in a subprocess whose ``sys.meta_path`` refuses to import ``cv2`` (as if
opencv-python were not installed).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

NO_OPENCV = '''
import sys

class NoOpenCV:
    """Refuses cv2 as a missing package would."""

    def find_spec(self, name, path=None, target=None):
        if name == "cv2" or name.startswith("cv2."):
            raise ModuleNotFoundError("No module named 'cv2' (blocked by the test)", name=name)
        return None

sys.meta_path.insert(0, NoOpenCV())
'''


def run_without_opencv(code: str, *args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", NO_OPENCV + code, *args], capture_output=True,
                          text=True, cwd=cwd, timeout=300)


def test_the_block_works(tmp_path):
    proc = run_without_opencv("import cv2", cwd=tmp_path)
    assert proc.returncode == 1 and "blocked by the test" in proc.stderr


@pytest.fixture
def drives(tmp_path: Path, rng: np.random.Generator) -> list[Path]:
    """Two noisy drives over the same 200 places, as .npy files of 24-d descriptors."""
    places = rng.standard_normal((200, 24)).astype(np.float32)
    paths = []
    for name in ("monday", "tuesday"):
        path = tmp_path / f"{name}.npy"
        np.save(path, places + 0.05 * rng.standard_normal(places.shape).astype(np.float32))
        paths.append(path)
    return paths


def test_cli_on_precomputed_descriptors(tmp_path, drives):
    cli = "from sprint_map.cli.main import main\nmain()\n"
    steps = [["init", "city.map", "--dim", "24"],
             ["ingest", "city.map", str(drives[0])],
             ["ingest", "city.map", str(drives[1]), "--json"],
             ["localize", "city.map", str(drives[1]), "--json"],
             ["info", "city.map", "--json"],
             ["check", "city.map"]]
    out = {}
    for args in steps:
        proc = run_without_opencv(cli, *args, cwd=tmp_path)
        assert proc.returncode == 0, (args, proc.stderr[-2000:])
        out[args[0]] = proc.stdout
    ingest = json.loads(out["ingest"])
    assert ingest["frames"] == 200 and ingest["edges_added"] > 0
    decisions = json.loads(out["localize"])["decisions"]
    assert sum(d["seq_id"] is not None for d in decisions) > 150
    assert json.loads(out["info"])["vertices"] == 400


def test_library_on_precomputed_descriptors(tmp_path, drives):
    code = f'''
import numpy as np
import sprint_map
from sprint_map import MapConfig, SprintMap

first, second = np.load({str(drives[0])!r}), np.load({str(drives[1])!r})
with SprintMap.create("lib.map", MapConfig(dim=24)) as m:
    m.add_sequence(first, name="monday")
    result = m.ingest(second, name="tuesday")
with SprintMap.open("lib.map", readonly=True) as m:
    decisions, _ = m.localize(second)
    assert m.check().ok
print(result.added.edges_added, sum(d.is_match for d in decisions), "cv2" in sys.modules)
'''
    proc = run_without_opencv(code, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    edges, matched, cv2_loaded = proc.stdout.split()
    assert int(edges) > 0 and int(matched) > 150 and cv2_loaded == "False"


def test_latent_worlds_need_no_opencv(tmp_path):
    """The latent family is numpy only: generated and opened as a data set with cv2 blocked."""
    code = ("from sprint_map.synth.latent import LATENT_PRESETS, generate_latent\n"
            "import dataclasses, sys\n"
            "from sprint_map.frontend.dataset import Dataset\n"
            "config = dataclasses.replace(LATENT_PRESETS['latent'], grid=(3, 3), dim=16)\n"
            "out = generate_latent('world', 2, 40, seed=0, config=config)\n"
            "data = Dataset.open(out)\n"
            "print(data.names, data.twin_frames(data.names[1]).shape, 'cv2' in sys.modules)\n")
    proc = run_without_opencv(code, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "['t00-day', 't01-overcast'] (40,) False"
