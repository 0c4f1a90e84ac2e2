"""A small map for the export tests: drives with and without positions, edges with
provenance, a removed drive (a gap in the vertex ids)."""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.config import MapConfig
from sprint_map.map import SprintMap
from sprint_map.storage.records import EdgeSpec


@pytest.fixture
def small_map(tmp_path, rng):
    """Drives a (positions x, y, heading), b (none), gone (removed), c (positions x, y), d
    (one frame, positions); edges both ways a-b, a-c one way, b-c without a frame."""
    path = tmp_path / "small.map"

    def rows(n):
        return rng.standard_normal((n, 8)).astype(np.float32)

    with SprintMap.create(path, MapConfig(dim=8)) as m:
        m.add_sequence(rows(20), name="a", positions=rng.uniform(-50, 50, (20, 3)))
        m.add_sequence(rows(12), name="b", edges=[
            EdgeSpec((None, 1), (0, 3), 0.75, 1), EdgeSpec((0, 3), (None, 1), 0.75, 1)])
        m.add_sequence(rows(6), name="gone", edges=[EdgeSpec((None, 0), (0, 0), 0.5, 0)])
        m.add_sequence(rows(15), name="c, \"quoted\"", source="drives/c/",
                       positions=rng.uniform(-50, 50, (15, 2)),
                       edges=[EdgeSpec((None, 2), (0, 5), 0.9, 2), EdgeSpec((1, 4), (None, 9), 0.5)])
        m.add_sequence(rows(1), name="d", positions=[[1.5, -2.5]])
        m.remove_sequences(["gone"])
    return path
