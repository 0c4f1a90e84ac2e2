"""UTM projection (Krüger series) against known values, and its inverse."""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.errors import InputError
from sprint_map.util.geo import GeoFrame, lonlat_of_utm, utm_of_lonlat, utm_zone

# WGS84 meridian arc from the equator to 45 degrees and to the pole (metres).
ARC_45 = 4984944.378
QUARTER_MERIDIAN = 10001965.729


def test_central_meridian_is_the_scaled_meridian_arc():
    east, north = utm_of_lonlat(45.0, 9.0, 32, False)
    assert east == pytest.approx(500000.0, abs=1e-6)
    assert north == pytest.approx(0.9996 * ARC_45, abs=1e-3)
    _, near_pole = utm_of_lonlat(89.999, 9.0, 32, False)  # 1/1000 degree: 111.69 m short
    assert near_pole == pytest.approx(0.9996 * (QUARTER_MERIDIAN - 111.69), abs=0.05)
    _, south = utm_of_lonlat(-45.0, 9.0, 32, True)
    assert south == pytest.approx(10_000_000 - 0.9996 * ARC_45, abs=1e-3)


def test_scale_factor_off_the_meridian():
    # Grid scale grows as 1 + x^2 / (2 R^2) away from the central meridian: 214 km east of it
    # (3 degrees at 50N) a step along the meridian is 1.00056 times longer than on it.
    lat = np.array([50.0, 50.0 + 1e-5])
    e0, n0 = utm_of_lonlat(lat, 9.0, 32, False)
    e3, n3 = utm_of_lonlat(lat, 12.0, 32, False)
    x = e3[0] - 500_000.0
    ratio = np.hypot(e3[1] - e3[0], n3[1] - n3[0]) / np.hypot(e0[1] - e0[0], n0[1] - n0[0])
    assert ratio == pytest.approx(1 + x**2 / (2 * 6_381_000.0**2), abs=2e-5)
    assert 210_000 < x < 220_000


def test_round_trip_below_a_millimetre_over_the_world():
    rng = np.random.default_rng(0)
    lat, lon = rng.uniform(-80, 84, 2000), rng.uniform(-180, 180, 2000)
    for a, b in zip(lat, lon, strict=True):
        zone, south = utm_zone(b), a < 0
        la, lo = lonlat_of_utm(*utm_of_lonlat(a, b, zone, south), zone, south)
        assert abs(la - a) * 111_320 < 1e-3
        assert abs(lo - b) * 111_320 * np.cos(np.radians(a)) < 1e-3


def test_frame_of_a_fix_and_its_record():
    frame = GeoFrame.for_fix(-33.9, 18.4)  # Cape Town
    assert (frame.zone, frame.south, frame.epsg) == (34, True, 32734)
    assert GeoFrame.from_dict(frame.to_dict()) == frame
    xy = frame.project([-33.9], [18.4])
    np.testing.assert_allclose(frame.unproject(xy[:, 0], xy[:, 1]), [[18.4, -33.9]], atol=1e-9)
    with pytest.raises(InputError, match="UTM zone must be 1..60"):
        GeoFrame(61)
    with pytest.raises(InputError, match="not a geographic frame"):
        GeoFrame.from_dict({"crs": "local"})
