"""A join whose drives are localised as Ray tasks equals the serial join."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map.config import MapConfig
from sprint_map.fleet.join import farm_localise_join
from sprint_map.map import SprintMap
from tests.helpers.worlds import drive, road_places


def test_join_with_ray_equals_the_serial_join(tmp_path: Path, cluster: Any) -> None:
    rng = np.random.default_rng(5)
    places = road_places(rng, 200, 16, corr=0.8)
    target, source = tmp_path / "t", tmp_path / "s"
    with SprintMap.create(target, MapConfig(dim=16)) as m:
        m.ingest(drive(places[:120], rng), name="t0")
    with SprintMap.create(source, MapConfig(dim=16)) as m:
        for i, lo in enumerate((40, 60, 160)):
            m.ingest(drive(places[lo : lo + 40], rng), name=f"s{i}")
    serial = tmp_path / "serial"
    shutil.copytree(target, serial)
    with SprintMap.open(serial) as m:
        want = m.join(source).to_dict()
        want_edges = [(e.to_dict(), e.frame) for e in m.edges()]
    with SprintMap.open(target) as m:
        got = m.join(source, localise_many=farm_localise_join(str(target), str(source))
                     ).to_dict()
        got_edges = [(e.to_dict(), e.frame) for e in m.edges()]
        assert m.check().ok
    assert got_edges == want_edges and got["drives"] == want["drives"]
