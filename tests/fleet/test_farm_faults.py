"""Faults of the ingest farm, with real kills: a worker SIGKILLed mid-task (Ray retries it),
the writer SIGKILLed mid-ingest (the map passes check; running again completes it)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sprint_map.fleet.farm import farm_ingest
from sprint_map.map import SprintMap
from tests.helpers.fleet import (
    NOISE,
    areas_of,
    base_map,
    copy_map,
    processes_titled,
    raylets,
    save_drives,
    serial_ingest,
    snapshot,
)
from tests.helpers.worlds import drive

pytestmark = pytest.mark.ray

TASK_TITLE = "ray::localise_drive"


class Killer(threading.Thread):
    """SIGKILLs the first process seen running a farm task (once)."""

    def __init__(self, parents: set[int]) -> None:
        super().__init__(daemon=True)
        self.parents = parents
        self.killed: int | None = None
        self.stop = threading.Event()

    def run(self) -> None:
        while not self.stop.is_set() and self.killed is None:
            for pid in processes_titled(TASK_TITLE, self.parents):
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    continue
                self.killed = pid
                return
            time.sleep(0.002)


@pytest.fixture
def fleet(tmp_path: Path, rng: np.random.Generator) -> tuple[Path, list[str]]:
    areas = areas_of(rng, 5)
    base = base_map(tmp_path / "base.map", areas[:3], rng)
    sources = save_drives(tmp_path / "drives",
                          [drive(areas[a], rng, NOISE) for a in (0, 1, 3, 2, 0, 4)])
    return base, sources


def test_a_worker_killed_mid_task_loses_and_duplicates_no_drive(
        cluster: Any, tmp_path: Path, fleet: tuple[Path, list[str]]) -> None:
    base, sources = fleet
    serial = copy_map(base, tmp_path / "serial.map")
    serial_ingest(serial, sources)
    farmed = copy_map(base, tmp_path / "farm.map")
    killer = Killer(raylets(cluster))
    killer.start()
    try:
        with SprintMap.open(farmed) as m:
            results = farm_ingest(m, sources)
    finally:
        killer.stop.set()
        killer.join()
    assert killer.killed is not None, "no farm task was seen running"
    assert snapshot(farmed) == snapshot(serial)
    assert not any(r.result.added.already_committed for r in results)


WRITER = """
import sys
from sprint_map.fleet.farm import farm_ingest
from sprint_map.fleet.runtime import connect
from sprint_map.map import SprintMap

def committed(r):
    print(r.result.added.sequence.name, r.result.added.already_committed, flush=True)
    if sys.argv[3] == "pause":  # hold after each commit until told to go on (or killed)
        sys.stdin.readline()

connect(sys.argv[1])
with SprintMap.open(sys.argv[2]) as m:
    farm_ingest(m, sys.argv[4:], window=2, on_commit=committed)
"""


def test_the_writer_killed_leaves_a_map_check_passes_and_a_rerun_completes(
        cluster: Any, tmp_path: Path, fleet: tuple[Path, list[str]]) -> None:
    """Killed between two commits (the store's own crash tests kill inside a commit)."""
    base, sources = fleet
    address = cluster.address  # type: ignore[attr-defined]
    serial = copy_map(base, tmp_path / "serial.map")
    serial_ingest(serial, sources)
    farmed = copy_map(base, tmp_path / "farm.map")
    cmd = [sys.executable, "-c", WRITER, address, str(farmed)]
    proc = subprocess.Popen([*cmd, "pause", *sources], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    assert proc.stdout.readline().strip(), "the writer committed nothing"
    proc.send_signal(signal.SIGKILL)  # the next drives are in flight on the cluster
    assert proc.wait(timeout=120) == -signal.SIGKILL
    with SprintMap.open(farmed, readonly=True) as m:
        assert m.check().ok
        done = len(m.sequences()) - 3
    assert done == 1
    rerun = subprocess.run([*cmd, "go", *sources], capture_output=True, text=True,
                           timeout=300, check=True)
    flags = [line.split()[1] for line in rerun.stdout.splitlines()]
    assert flags == ["True"] * done + ["False"] * (len(sources) - done)  # none added twice
    assert snapshot(farmed) == snapshot(serial)
