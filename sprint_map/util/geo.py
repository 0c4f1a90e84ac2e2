"""Geodesy by pyproj (PROJ): WGS84 latitude/longitude <-> UTM metres, geodesic distances and
interpolation, and the map's stored geographic frame.

A map that is given latitude/longitude stores its positions in ONE Universal Transverse Mercator
zone (:class:`GeoFrame`), chosen from the first fix it is given and kept for every later drive,
even one that lies in a neighbouring zone, across the antimeridian or near a pole. UTM rather
than a local tangent plane because the VPR benchmarks' file names carry UTM eastings/northings
already (their ground truth is a radius in those metres) and because a UTM frame needs no origin
that the first drive would have to fix.

The projection is PROJ's ``utm`` (EPSG:326zz/327zz), the Poder/Engsager extended transverse
Mercator: millimetre round trips far beyond a zone's 6 degrees (a drive in the next zone, or on
the other side of the antimeridian, is projected without a seam), and defined up to the poles
(UTM's usual limits of 84N/80S are a convention of its grid, not of the projection). Its grid
scale grows away from the zone's central meridian (1.0004 at 3 degrees, 1.0030 at 6 degrees at
the equator): a map spanning continents should be split. Geodesics (distances, and the points
between two fixes) are Karney's on the WGS84 ellipsoid (``pyproj.Geod``): exact across the
antimeridian and over the poles, where a mean of longitudes is not.

pyproj is imported on first use (``Transformer`` objects cached per zone; thread-safe since
pyproj 3.1). O(n) per call, vectorised.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from sprint_map.errors import InputError
from sprint_map.util.arrays import Float64Array

__all__ = ["GeoFrame", "geodesic_distance", "geodesic_points", "lonlat_of_utm",
           "utm_of_lonlat", "utm_zone"]


def utm_zone(lon_deg: float) -> int:
    """The UTM zone number (1..60) of a longitude (the regular 6-degree zones). O(1)."""
    return int((math.floor((lon_deg + 180.0) / 6.0) % 60) + 1)


def _epsg(zone: int, south: bool) -> int:
    return (32700 if south else 32600) + zone


@functools.lru_cache(maxsize=16)
def _transformer(epsg: int, inverse: bool) -> Any:
    from pyproj import Transformer

    crs = ("EPSG:4326", f"EPSG:{epsg}")
    return Transformer.from_crs(*(crs[::-1] if inverse else crs), always_xy=True)


@functools.lru_cache(maxsize=1)
def _geod() -> Any:
    from pyproj import Geod

    return Geod(ellps="WGS84")


def _pair(a: Any, b: Any) -> tuple[Float64Array, Float64Array]:
    """Two coordinate arrays broadcast to one shape, float64 copies (PROJ works in place)."""
    x, y = np.broadcast_arrays(np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64))
    return np.array(x), np.array(y)


def _domain(*arrays: Float64Array) -> None:
    """PROJ gives Inf for a point it cannot place; NaN stays NaN (no fix)."""
    for arr in arrays:
        arr[np.isinf(arr)] = np.nan


def utm_of_lonlat(lat_deg: Any, lon_deg: Any, zone: int, south: bool
                  ) -> tuple[Float64Array, Float64Array]:
    """Project WGS84 latitude/longitude (degrees) to ``(easting, northing)`` metres in UTM
    ``zone`` (northern or ``south``ern hemisphere false northing). NaN in (or a latitude
    beyond +-90) gives NaN out. O(n)."""
    lat, lon = _pair(lat_deg, lon_deg)
    east, north = _transformer(_epsg(zone, south), False).transform(lon, lat)
    east, north = np.array(east, dtype=np.float64), np.array(north, dtype=np.float64)
    _domain(east, north)
    return east, north


def lonlat_of_utm(east: Any, north: Any, zone: int, south: bool
                  ) -> tuple[Float64Array, Float64Array]:
    """Inverse of :func:`utm_of_lonlat`: ``(lat_deg, lon_deg)`` of UTM metres (longitude in
    [-180, 180]). O(n)."""
    e, n = _pair(east, north)
    lon, lat = _transformer(_epsg(zone, south), True).transform(e, n)
    lat, lon = np.array(lat, dtype=np.float64), np.array(lon, dtype=np.float64)
    _domain(lat, lon)
    return lat, lon


def geodesic_distance(a_latlon: Any, b_latlon: Any) -> Float64Array:
    """Metres along the WGS84 geodesic between the ``(n, 2)`` latitude/longitude rows of
    ``a_latlon`` and ``b_latlon`` (NaN where either is NaN). O(n)."""
    a = np.asarray(a_latlon, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(b_latlon, dtype=np.float64).reshape(-1, 2)
    out = np.full(len(a), np.nan)
    ok = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
    if ok.any():
        _, _, dist = _geod().inv(a[ok, 1], a[ok, 0], b[ok, 1], b[ok, 0])
        out[ok] = dist
    return out


def geodesic_points(a_latlon: Any, b_latlon: Any, fraction: Any) -> Float64Array:
    """``(n, 2)`` latitude/longitude of the points a ``fraction`` (0: ``a``, 1: ``b``) of the
    way along the WGS84 geodesic from each row of ``a_latlon`` to the same row of
    ``b_latlon``: what lies between two fixes, across the antimeridian and the poles alike
    (longitude in [-180, 180]; NaN where either end is NaN). O(n)."""
    a = np.asarray(a_latlon, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(b_latlon, dtype=np.float64).reshape(-1, 2)
    w = np.broadcast_to(np.asarray(fraction, dtype=np.float64), (len(a),))
    out = np.full((len(a), 2), np.nan)
    ok = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1) & np.isfinite(w)
    if not ok.any():
        return out
    geod = _geod()
    azimuth, _, dist = geod.inv(a[ok, 1], a[ok, 0], b[ok, 1], b[ok, 0])
    lon, lat, _ = geod.fwd(a[ok, 1], a[ok, 0], azimuth, np.asarray(dist) * w[ok])
    out[ok, 0], out[ok, 1] = lat, lon
    ends = ok & ((w == 0) | (w == 1))  # the fixes themselves, bit for bit
    out[ends] = np.where((w[ends] == 0)[:, None], a[ends], b[ends])
    return out


@dataclass(frozen=True)
class GeoFrame:
    """The metric frame a map keeps latitude/longitude positions in: one UTM zone.

    ``zone`` 1..60; ``south`` selects the southern hemisphere's false northing (10,000 km).
    Stored in the map as :meth:`to_dict` (``{"crs": "utm", "zone": 33, "south": false,
    "epsg": 32633}``), the meta record ``geo_frame``.
    """

    zone: int
    south: bool = False

    def __post_init__(self) -> None:
        if isinstance(self.zone, bool) or not isinstance(self.zone, int) or not 1 <= self.zone <= 60:
            raise InputError(f"UTM zone must be 1..60, got {self.zone!r}")

    @classmethod
    def for_fix(cls, lat_deg: float, lon_deg: float) -> GeoFrame:
        """The zone and hemisphere of one fix (the first a map is given). O(1)."""
        return cls(utm_zone(lon_deg), lat_deg < 0)

    @property
    def epsg(self) -> int:
        """The EPSG code of this zone (326zz north, 327zz south)."""
        return _epsg(self.zone, self.south)

    def project(self, lat_deg: Any, lon_deg: Any) -> Float64Array:
        """``(n, 2)`` easting, northing of ``n`` fixes. O(n)."""
        east, north = utm_of_lonlat(lat_deg, lon_deg, self.zone, self.south)
        return np.stack([np.atleast_1d(east), np.atleast_1d(north)], axis=1)

    def unproject(self, east: Any, north: Any) -> Float64Array:
        """``(n, 2)`` longitude, latitude (GeoJSON's order) of ``n`` points. O(n)."""
        lat, lon = lonlat_of_utm(east, north, self.zone, self.south)
        return np.stack([np.atleast_1d(lon), np.atleast_1d(lat)], axis=1)

    def to_dict(self) -> dict[str, Any]:
        return {"crs": "utm", "zone": self.zone, "south": self.south, "epsg": self.epsg}

    @classmethod
    def from_dict(cls, data: Any) -> GeoFrame:
        """Inverse of :meth:`to_dict`; InputError on anything else."""
        if (not isinstance(data, dict) or data.get("crs") != "utm"
                or not isinstance(data.get("south"), bool)):
            raise InputError(f"not a geographic frame record: {data!r}")
        return cls(data["zone"], data["south"])
