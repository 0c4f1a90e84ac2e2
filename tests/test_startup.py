"""What start-up loads: ``import sprint_map`` its configuration, not the image front end;
``sprint-map info`` LMDB, not the HMM, FAISS or OpenCV (``tools/bench_startup.py`` times it)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sprint_map import MapConfig, SprintMap


def loaded_after(statement: str) -> set[str]:
    code = f"import sys; {statement}; print(' '.join(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    return set(out.split())


def test_import_sprint_map_loads_neither_opencv_nor_data_sets():
    mods = loaded_after("import sprint_map")
    assert "cv2" not in mods and "scipy.spatial" not in mods
    assert "sprint_map.frontend.dataset" not in mods


def test_the_front_end_loads_opencv_when_an_image_is_described():
    mods = loaded_after(
        "import numpy as np; from sprint_map.frontend import DescriptorSpec; "
        "DescriptorSpec('hog').describe(np.zeros((48, 64, 3), np.uint8))")
    assert "cv2" in mods


def test_nothing_imports_ray_without_ray_asked_for():
    """Ray (the optional extra) loads only with ``--ray`` or sprint_map.fleet's functions."""
    mods = loaded_after("import sprint_map.cli.main, sprint_map.map, sprint_map.server.run, "
                        "sprint_map.fleet.runtime, sprint_map.fleet.shards, "
                        "sprint_map.fleet.farm, sprint_map.fleet.replicas")
    assert "ray" not in mods


# --- sprint-map info reads LMDB only --------------------------------------------------------

#: What a command that only reads LMDB must not import.
HEAVY = ("faiss", "scipy", "cv2", "matplotlib", "networkx", "rich", "fastapi", "uvicorn",
         "pyproj", "onnx", "onnxruntime")

# Runs the CLI in this process, then lists what it imported (at exit: main() exits).
CLI_MODULES = ("import atexit, sys\n"
               "atexit.register(lambda: print(' '.join(sorted(sys.modules)), file=sys.stderr))\n"
               "from sprint_map.cli.main import main\n"
               "main()\n")


def heavy_loaded(modules: set[str]) -> set[str]:
    """The heavy packages among ``modules``, and the HMM's modules beyond its config."""
    return ({m for m in modules if m.split(".")[0] in HEAVY}
            | {m for m in modules
               if m.startswith("sprint_map.hmm.") and m != "sprint_map.hmm.config"})


def cli_modules(*args: str) -> tuple[subprocess.CompletedProcess[str], set[str]]:
    proc = subprocess.run([sys.executable, "-c", CLI_MODULES, *args], capture_output=True,
                          text=True)
    return proc, set(proc.stderr.split())


@pytest.fixture(scope="module")
def small_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A map of two drives of random descriptors (the second merged: edges, one component)."""
    root = tmp_path_factory.mktemp("startup")
    rng = np.random.default_rng(7)
    road = rng.standard_normal((300, 32)).astype(np.float32)
    path = root / "city.map"
    with SprintMap.create(path, MapConfig(dim=32)) as m:
        m.add_sequence(road, name="monday")
        m.ingest(road + 0.05 * rng.standard_normal(road.shape).astype(np.float32), name="tue")
    return path


@pytest.mark.parametrize("args", [["info", "--json"], ["sequences"], ["components", "--json"]])
def test_reading_commands_import_no_hmm_opencv_or_scipy(small_map, args):
    proc, modules = cli_modules(args[0], str(small_map), *args[1:])
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert not heavy_loaded(modules), sorted(heavy_loaded(modules))


#: Standard modules a command that only reads LMDB has no use for: the index's sealing thread
#: pool (and logging with it), OpenSSL's hashes (digests are written or checked, not read), the
#: positions' CSV reader.
UNNEEDED_STDLIB = ("concurrent", "logging", "hashlib", "_hashlib", "csv")


def test_info_loads_no_standard_module_it_does_not_need(small_map):
    proc, modules = cli_modules("info", str(small_map), "--json")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert not {m.split(".")[0] for m in modules} & set(UNNEEDED_STDLIB)


#: The package's own modules ``info`` has no use for: the sources, the trace, the progress bar
#: and the output files (ingest and localize load them), compaction (compact and summarize),
#: the multiprocessing they bring.
UNNEEDED_OWN = ("sprint_map.frontend.sources", "sprint_map.frontend.bags",
                "sprint_map.frontend.positions", "sprint_map.localize.trace",
                "sprint_map.cli.progress", "sprint_map.util.output",
                "sprint_map.storage.compaction", "sprint_map.storage.reduction",
                "multiprocessing")


def test_info_loads_none_of_the_package_it_does_not_need(small_map):
    proc, modules = cli_modules("info", str(small_map), "--json")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert not modules & set(UNNEEDED_OWN), sorted(modules & set(UNNEEDED_OWN))


def test_sprint_map_cli_imports_no_opencv():
    assert "cv2" not in loaded_after("import sprint_map.cli.main")


def test_faiss_loads_with_the_first_search(small_map):
    code = ("import sys\n"
            "from sprint_map import SprintMap\n"
            f"with SprintMap.open({str(small_map)!r}, readonly=True) as m:\n"
            "    m.info()\n"
            "    before = 'faiss' in sys.modules\n"
            "    m.search(m.descriptors(0)[:3], 2)\n"
            "print(before, 'faiss' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    assert out == ["False", "True"]


def test_no_module_imports_faiss_at_load():
    """Every module of the package imports FAISS through ``util.lazy`` (on first use):
    importing all of them (those whose optional extra is installed) loads no FAISS."""
    code = ("import importlib, pkgutil, sys, sprint_map\n"
            "for mod in pkgutil.walk_packages(sprint_map.__path__, 'sprint_map.'):\n"
            "    try:\n"
            "        importlib.import_module(mod.name)\n"
            "    except ModuleNotFoundError as exc:\n"
            "        if (exc.name or '').startswith('sprint_map'):\n"
            "            raise\n"
            "print(len([m for m in sys.modules if m.startswith('sprint_map.')]),\n"
            "      'faiss' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout.split()
    assert int(out[0]) > 100 and out[1] == "False", out
