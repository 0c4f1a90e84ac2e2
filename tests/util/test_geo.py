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


# --- issue 52: the antimeridian, the poles, far beyond a zone ----------------------------------

def test_the_point_between_fixes_either_side_of_the_antimeridian_lies_between_them():
    from sprint_map.util.geo import geodesic_distance, geodesic_points

    a, b = [[-16.8, 179.9999]], [[-16.8, -179.9999]]  # Fiji: 21 m apart
    mid = geodesic_points(a, b, 0.5)
    assert geodesic_distance(a, b)[0] == pytest.approx(21.3, abs=0.1)
    assert geodesic_distance(a, mid)[0] == pytest.approx(geodesic_distance(a, b)[0] / 2, abs=1e-6)
    assert geodesic_distance(mid, b)[0] == pytest.approx(geodesic_distance(a, b)[0] / 2, abs=1e-6)
    quarter = geodesic_points(a, b, [0.25])
    assert geodesic_distance(a, quarter)[0] == pytest.approx(5.33, abs=0.01)


def test_the_point_between_fixes_either_side_of_a_pole_is_the_pole():
    from sprint_map.util.geo import geodesic_distance, geodesic_points

    a, b = [[89.99, 0.0]], [[89.99, 180.0]]  # 2.2 km apart, over the pole
    mid = geodesic_points(a, b, 0.5)
    assert mid[0, 0] == pytest.approx(90.0, abs=1e-9)
    assert geodesic_distance(a, b)[0] == pytest.approx(2 * geodesic_distance(a, mid)[0],
                                                       abs=1e-6)


def test_ends_nan_and_fractions_of_the_geodesic():
    from sprint_map.util.geo import geodesic_points

    a = np.array([[59.9, 10.7], [np.nan, np.nan], [1.0, 2.0]])
    b = np.array([[60.1, 10.9], [1.0, 2.0], [3.0, 4.0]])
    out = geodesic_points(a, b, np.array([0.0, 0.5, 1.0]))
    np.testing.assert_array_equal(out[0], a[0])
    assert np.isnan(out[1]).all()
    np.testing.assert_array_equal(out[2], b[2])


@pytest.mark.parametrize(("lat", "lon"), [(45.0, 60.0), (-30.0, -150.0), (70.0, 100.0),
                                          (89.9999, 123.0), (-89.9, -45.0)])
def test_round_trip_far_beyond_the_zone_and_near_the_poles(lat, lon):
    """A map's zone is kept for every later drive: one 45 degrees away, beyond the antimeridian
    or at a pole is still projected to the millimetre (a third-order series is not)."""
    frame = GeoFrame(33)
    xy = frame.project([lat], [lon])
    back = frame.unproject(xy[:, 0], xy[:, 1])[0]
    assert abs(back[1] - lat) * 111_320 < 1e-3
    assert abs((back[0] - lon + 180) % 360 - 180) * 111_320 * np.cos(np.radians(lat)) < 1e-3


def test_a_step_across_the_antimeridian_is_short_in_the_maps_frame():
    frame = GeoFrame.for_fix(-16.8, 179.9999)
    xy = frame.project([-16.8, -16.8], [179.9999, -179.9999])
    assert np.hypot(*(xy[1] - xy[0])) == pytest.approx(21.3, abs=0.1)
