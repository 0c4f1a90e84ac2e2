"""The ingest farm on a real 3-node Ray cluster: the result equals serial ingest in the same
order (same sequences, same edges), whether a drive's snapshot was still valid or not."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from sprint_map.config import StoreOptions
from sprint_map.fleet.farm import farm_ingest
from sprint_map.map import SprintMap
from tests.helpers.fleet import (
    NOISE,
    areas_of,
    base_map,
    copy_map,
    save_drives,
    serial_ingest,
    snapshot,
)
from tests.helpers.worlds import drive

pytestmark = pytest.mark.ray


@pytest.fixture
def fleet(tmp_path: Path, rng: np.random.Generator) -> tuple[Path, list[str]]:
    """A base map of areas 0-2 and six drives: revisits of 0, 1 and 2, area 0 again (after a
    farm drive merged into it: stale), and two new areas (3, 4)."""
    areas = areas_of(rng, 5)
    base = base_map(tmp_path / "base.map", areas[:3], rng)
    order = [0, 1, 0, 3, 2, 4]
    sources = save_drives(tmp_path / "drives", [drive(areas[a], rng, NOISE) for a in order])
    return base, sources


def test_farm_equals_serial_ingest(cluster: object, tmp_path: Path,
                                   fleet: tuple[Path, list[str]]) -> None:
    base, sources = fleet
    serial = copy_map(base, tmp_path / "serial.map")
    serial_ingest(serial, sources)
    farmed = copy_map(base, tmp_path / "farm.map")
    with SprintMap.open(farmed) as m:
        results = farm_ingest(m, sources, window=6)
    assert [r.source for r in results] == sources
    want, got = snapshot(serial), snapshot(farmed)
    assert got["sequences"] == want["sequences"]
    assert got["edges"] == want["edges"]
    assert got["components"] == want["components"]
    assert len(want["edges"]) > 0  # drives merged: the comparison is not between empty maps
    # both paths were taken: decisions made in parallel and committed as they were, and a
    # drive whose area a farm drive had merged into since its snapshot, localised again
    why = [r.relocalised for r in results]
    assert None in why
    assert any(w is not None and "since the snapshot" in w for w in why), why
    with SprintMap.open(farmed, readonly=True) as m:
        assert m.check().ok


def test_farm_on_an_empty_map_equals_serial(cluster: object, tmp_path: Path,
                                            rng: np.random.Generator) -> None:
    areas = areas_of(rng, 2)
    sources = save_drives(tmp_path / "drives", [drive(areas[a], rng, NOISE) for a in (0, 1, 0)])
    empty = tmp_path / "empty.map"
    from sprint_map.config import MapConfig
    from tests.helpers.fleet import DIM

    SprintMap.create(empty, MapConfig(dim=DIM, store=StoreOptions(index_type="flat"))).close()
    serial = copy_map(empty, tmp_path / "serial.map")
    serial_ingest(serial, sources)
    farmed = copy_map(empty, tmp_path / "farm.map")
    with SprintMap.open(farmed) as m:
        results = farm_ingest(m, sources, names=[None, "second", None])
    assert results[0].relocalised is None  # the first drive of an empty map: appended
    want = snapshot(serial)
    want["sequences"][1] = (*want["sequences"][1][:1], "second", *want["sequences"][1][2:])
    assert snapshot(farmed) == want
