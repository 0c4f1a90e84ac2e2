"""Helpers of the fleet tests: a small world of areas, drives over them, maps compared."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map.config import MapConfig
from sprint_map.map import SprintMap

DIM = 32
AREA = 60  # places per area


def world(rng: np.random.Generator, areas: int) -> list[np.ndarray]:
    """``areas`` areas of ``AREA`` unit-norm places each."""
    out = []
    for _ in range(areas):
        p = rng.standard_normal((AREA, DIM))
        out.append((p / np.linalg.norm(p, axis=1, keepdims=True)).astype(np.float32))
    return out


def drive(places: np.ndarray, rng: np.random.Generator, noise: float = 0.25) -> np.ndarray:
    """A noisy traversal of ``places``."""
    x = places + noise * rng.standard_normal(places.shape)
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def base_map(path: Path, areas: list[np.ndarray], rng: np.random.Generator) -> Path:
    """A map with one drive over each area (no edges)."""
    with SprintMap.create(path, MapConfig(dim=DIM, index_type="flat")) as m:
        for n, places in enumerate(areas):
            m.add_sequence(drive(places, rng), name=f"base{n}")
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
