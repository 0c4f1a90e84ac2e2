"""A frame's position between two GNSS fixes (issue 52): along the geodesic, so fixes either
side of the antimeridian or of a pole place the frame between them."""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.frontend.bags import interpolate_fixes
from sprint_map.util.geo import geodesic_distance


def _fixes(latlon):
    latlon = np.asarray(latlon, dtype=np.float64)
    n = len(latlon)
    return (np.arange(n, dtype=np.int64) * 1_000_000_000, latlon, np.full(n, 3.0),
            np.ones(n, dtype=bool))


@pytest.mark.parametrize(("a", "b"), [((-16.8, 179.9999), (-16.8, -179.9999)),
                                      ((65.0, -179.99995), (65.0, 179.99995)),
                                      ((89.9999, -90.0), (89.9999, 90.0))])
def test_a_frame_between_two_fixes_lies_between_them(a, b):
    """Linear in longitude, the frame halfway between fixes 21 m apart either side of the
    antimeridian landed 16,244 km away (the other side of the Earth)."""
    fix_ns, latlon, sigma, valid = _fixes([a, b])
    frames = np.array([250_000_000, 500_000_000, 750_000_000], dtype=np.int64)
    out, out_sigma = interpolate_fixes(frames, fix_ns, latlon, sigma, valid)
    apart = geodesic_distance([a], [b])[0]
    assert apart < 25
    for t, row in zip((0.25, 0.5, 0.75), out, strict=True):
        assert geodesic_distance([a], [row])[0] == pytest.approx(t * apart, abs=1e-3)
        assert geodesic_distance([row], [b])[0] == pytest.approx((1 - t) * apart, abs=1e-3)
        assert -180 <= row[1] <= 180
    np.testing.assert_allclose(out_sigma, 3.0)


def test_frames_at_and_beyond_the_fixes():
    fix_ns, latlon, sigma, valid = _fixes([(59.9, 10.7), (59.91, 10.71)])
    frames = np.array([-1, 0, 1_000_000_000, 1_000_000_001], dtype=np.int64)
    out, _ = interpolate_fixes(frames, fix_ns, latlon, sigma, valid)
    assert np.isnan(out[[0, 3]]).all()
    np.testing.assert_array_equal(out[1:3], latlon)
