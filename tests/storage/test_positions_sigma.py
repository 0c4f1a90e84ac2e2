"""Positions with a fix accuracy (sigma_m) and frames without a fix, through the store; the
stored geographic frame."""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.config import MapConfig
from sprint_map.errors import InputError
from sprint_map.frontend.positions import Positions
from sprint_map.map import SprintMap
from sprint_map.storage.keys import VERTEX_VAL, u64

DIM = 8


def rows(n: int, seed: int) -> np.ndarray:
    x = np.random.default_rng(seed).standard_normal((n, DIM)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def raw_values(m: SprintMap, first: int, n: int) -> list[bytes | None]:
    with m.store.env.read() as txn:
        db = m.store.env.db("vertex_data")
        return [None if (v := txn.get(u64(first + i), db=db)) is None else bytes(v)
                for i in range(n)]


def test_sigma_and_missing_fixes_round_trip(tmp_path):
    pos = np.array([[1, 2, 90, 10, 0.5], [np.nan] * 5, [3, 4, np.nan, 11, np.nan],
                    [5, 6, 0, np.nan, 2.0]])
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        m.add_sequence(rows(4, 0), name="a", positions=pos)
        m.add_sequence(rows(3, 1), name="b", positions=np.arange(9.0).reshape(3, 3))
        first = [m.sequence_by_name("a").first_vertex, m.sequence_by_name("b").first_vertex]
    with SprintMap.open(tmp_path / "m", readonly=True) as m:
        got = m.positions(0)
        np.testing.assert_array_equal(got, pos)  # NaN where NaN, sigma kept
        # a frame without a fix has no record; one without sigma keeps today's 32 bytes
        sizes = [None if v is None else len(v) for v in raw_values(m, first[0], 4)]
        assert sizes == [40, None, VERTEX_VAL.size, 40]
        # a drive without sigma: today's (n, 4) records and array, unchanged
        assert m.positions(1).shape == (3, 4)
        assert {len(v) for v in raw_values(m, first[1], 3)} == {VERTEX_VAL.size}
        assert m.check().ok


def test_first_frame_without_a_fix_still_has_positions(tmp_path):
    pos = np.array([[np.nan, np.nan], [1.0, 2.0]])
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        m.add_sequence(rows(2, 0), positions=pos)
        np.testing.assert_array_equal(m.positions(0)[:, :2], pos)


@pytest.mark.parametrize(("bad", "message"), [
    ([[1.0, np.nan]], "NaN or Inf in x or y"),
    ([[np.inf, 1.0]], "NaN or Inf in x or y"),
    ([[1.0, 1.0, 0, 0, 0.0]], "sigma_m must be NaN or a finite value > 0"),
    ([[1.0, 1.0, 0, 0, -1.0]], "sigma_m must be NaN or a finite value > 0"),
    ([[1.0, 1.0, 0, 0, 1.0, 1.0]], "positions must be 1 rows"),
])
def test_bad_positions_change_nothing(tmp_path, bad, message):
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        with pytest.raises(InputError, match=message):
            m.add_sequence(rows(1, 0), positions=np.array(bad))
        assert m.stats()["sequences"] == 0


def test_geographic_positions_share_the_first_drives_zone(tmp_path):
    near_oslo = Positions(np.arange(2), np.array([[59.9, 10.7], [59.91, 10.7]]),
                          sigma_m=np.array([1.0, np.nan]), geographic=True)
    # the next drive lies in the neighbouring zone (33): still projected into zone 32
    east = Positions(np.arange(1), np.array([[59.9, 12.5]]), geographic=True)
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        assert m.geo_frame() is None
        a = m.metric_positions(near_oslo)
        assert m.geo_frame().to_dict() == {"crs": "utm", "zone": 32, "south": False,
                                           "epsg": 32632}
        b = m.metric_positions(east)
        assert m.geo_frame().zone == 32
    assert a.shape == (2, 5) and a[0, 4] == 1.0 and np.isnan(a[1, 4])
    assert a[1, 1] - a[0, 1] == pytest.approx(1113.0, rel=2e-3)  # 0.01 degree of latitude
    assert b[0, 0] > 600_000  # east of zone 32's central meridian, not zone 33's 500 km
    with SprintMap.open(tmp_path / "m", readonly=True) as m:  # stored
        assert m.geo_frame().zone == 32
