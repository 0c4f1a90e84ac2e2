"""Helpers of the fleet tests: a small world of areas, drives over them, maps compared."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map.config import MapConfig, StoreOptions
from sprint_map.map import SprintMap
from tests.helpers.worlds import drive, random_places

DIM = 32
AREA = 60  # places per area


NOISE = 0.25  # of the fleet tests' drives (:func:`tests.helpers.worlds.drive`)


def areas_of(rng: np.random.Generator, areas: int) -> list[np.ndarray]:
    """``areas`` areas of ``AREA`` independent places each."""
    return [random_places(rng, AREA, DIM) for _ in range(areas)]


def base_map(path: Path, areas: list[np.ndarray], rng: np.random.Generator) -> Path:
    """A map with one drive over each area (no edges)."""
    with SprintMap.create(path, MapConfig(dim=DIM, store=StoreOptions(index_type="flat"))) as m:
        for n, places in enumerate(areas):
            m.add_sequence(drive(places, rng, NOISE), name=f"base{n}")
    return path


def copy_map(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def save_drives(directory: Path, drives: list[np.ndarray]) -> list[str]:
    directory.mkdir(parents=True, exist_ok=True)
    paths = []
    for n, rows in enumerate(drives):
        p = directory / f"drive{n:02d}.npy"
        np.save(p, rows)
        paths.append(str(p))
    return paths


def serial_ingest(path: Path, sources: list[str]) -> None:
    """What ``sprint-map ingest`` does for each source in turn."""
    with SprintMap.open(path) as m:
        for source in sources:
            src = m.open_source(source)
            m.ingest(src.iter_batches(), name=src.name, source=source)


def snapshot(path: Path) -> dict[str, Any]:
    """Sequences, edges and components of a map, for comparing two maps."""
    with SprintMap.open(path, readonly=True) as m:
        return {
            "sequences": [(s.seq_id, s.name, s.length, s.first_vertex) for s in m.sequences()],
            # all but the commit time
            "edges": [(e.src_seq, e.src_image, e.dst_seq, e.dst_image, e.prob, e.added_by,
                       e.frame) for e in m.edges()],
            "components": sorted((c.component, tuple(c.sequences)) for c in m.components()),
        }


class Server:
    """A ``sprint-map serve MAP --port 0 ...`` subprocess, ready when constructed."""

    def __init__(self, map_path: Path, log: Path, *args: str, timeout: float = 120.0) -> None:
        import subprocess
        import sys
        import time

        import httpx

        cmd = [sys.executable, "-c", "from sprint_map.cli.main import main; main()", "serve",
               str(map_path), "--port", "0", *args]
        self.log = log
        self._err = log.open("w")
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=self._err, text=True)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        assert line.startswith("serving "), f"no announcement: {line!r} {log.read_text()}"
        self.client = httpx.Client(base_url=line.split(" on ", 1)[1].strip(), timeout=60)
        deadline = time.monotonic() + timeout
        while self.client.get("/readyz").status_code != 200:
            assert time.monotonic() < deadline and self.proc.poll() is None, log.read_text()
            time.sleep(0.05)

    def session(self) -> str:
        response = self.client.post("/v1/sessions", json={})
        assert response.status_code in (200, 201), response.text
        return str(response.json()["session_id"])

    def frame(self, session: str, row: np.ndarray) -> Any:
        return self.client.post(f"/v1/sessions/{session}/frames",
                                content=np.asarray(row, np.float32).tobytes(),
                                headers={"content-type": "application/octet-stream"})

    def close(self) -> None:
        self.client.close()
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(60)
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self._err.close()


def raylets(cluster: Any) -> set[int]:
    """Pids of the raylets of ``cluster`` (a ``ray.cluster_utils.Cluster``): its workers are
    their children."""
    return {p.process.pid for node in cluster.list_all_nodes()
            for p in node.all_processes.get("raylet", [])}


def processes_titled(title: str, parents: set[int]) -> list[int]:
    """Pids of the children of ``parents`` whose command line starts with ``title`` (the
    title Ray gives a worker running a task or an actor: other Ray sessions on the machine
    are left alone)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                cmd = (entry / "cmdline").read_bytes()
                ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
            if cmd.startswith(title.encode()) and ppid in parents:
                pids.append(int(entry.name))
    return pids
