"""The VPR benchmarks' layout: ``database/`` and ``queries/`` folders of images whose names
carry their place.

The widely used evaluation code (Berton et al., "Deep Visual Geo-localization Benchmark") names
each image ``@UTM_east@UTM_north@UTM_zone_number@UTM_zone_letter@lat@lon@pano_id@tile_num@
heading@pitch@roll@height@timestamp@note@.jpg``: fields split on ``@``, the first (before the
leading ``@``) empty or a prefix, the 13th the timestamp (often empty). A data set is a folder
holding ``database/`` and ``queries/`` (or ``images/test/database`` and ``images/test/queries``
as the benchmark's downloads lay them out).

Frames are taken in the order of their timestamps when every name of the folder has one (the
13th field, a number), else in natural file-name order (:func:`vpr_order` says which): SPRINT
needs a sequence. Positions are the names' UTM eastings/northings, converted to WGS84
latitude/longitude (exactly, :func:`sprint_map.util.geo.lonlat_of_utm`) so a map keeps them in
its own UTM zone like any other fix. O(files) per folder.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sprint_map.errors import InputError
from sprint_map.frontend.imagefiles import list_images, natural_key
from sprint_map.frontend.positions import Positions
from sprint_map.util.arrays import Float64Array
from sprint_map.util.geo import lonlat_of_utm

__all__ = ["VprDataset", "VprName", "is_vpr_folder", "is_vpr_name", "parse_vpr_name",
           "vpr_order", "vpr_positions"]

_NAME_FORMAT = "@UTM_east@UTM_north@zone_number@zone_letter@lat@lon@...@timestamp@..."
_SOUTH_LETTERS = set("CDEFGHJKLM")


@dataclass(frozen=True)
class VprName:
    """What one file name says: UTM position (zone, hemisphere), lat/lon and timestamp."""

    east: float
    north: float
    zone: int
    south: bool
    lat: float
    lon: float
    timestamp: float | None


def parse_vpr_name(path: Path) -> VprName:
    """Parse a VPR-layout file name.

    Raises
    ------
    InputError
        One line naming the file: fewer than 13 ``@`` fields, or an easting, northing, zone
        number (1-60) or zone letter (C-X) that is not one.
    """
    fields = path.name.split("@")
    bad = f"{path}: not a VPR-layout name ({_NAME_FORMAT})"
    if len(fields) < 14:
        raise InputError(bad)
    try:
        east, north, zone = float(fields[1]), float(fields[2]), int(fields[3])
    except ValueError:
        raise InputError(bad + ": no UTM easting/northing/zone") from None
    letter = fields[4].strip().upper()
    if (not (math.isfinite(east) and math.isfinite(north)) or not 1 <= zone <= 60
            or len(letter) != 1 or not "C" <= letter <= "X" or letter in "IO"):
        raise InputError(bad + f": UTM zone {fields[3]!r}{fields[4]!r} or coordinates invalid")
    south = letter in _SOUTH_LETTERS
    lat, lon = lonlat_of_utm(east, north, zone, south)
    stamp = fields[13].strip()
    try:
        timestamp: float | None = float(stamp) if stamp else None
    except ValueError:
        timestamp = None
    return VprName(east, north, zone, south, float(lat), float(lon), timestamp)


def is_vpr_name(name: str) -> bool:
    """Whether ``name`` has the VPR layout's shape: 14 or more ``@`` fields, the first a prefix
    or empty (``img059@east@north@...`` as well as ``@east@north@...``); whether its fields
    hold a place is :func:`parse_vpr_name`'s to say."""
    return name.count("@") >= 13


def is_vpr_folder(files: list[Path]) -> bool:
    """Whether a folder's images are taken as the VPR layout (every name one,
    :func:`is_vpr_name`): the one rule that the map builder (``ingest``, ``localize``, an
    image folder's source) and :class:`VprDataset` (``eval --layout vpr``) both apply, so
    both order and place the frames alike. O(files)."""
    return bool(files) and all(is_vpr_name(f.name) for f in files)


def vpr_order(files: list[Path]) -> tuple[list[Path], str]:
    """``files`` in timestamp order when every name carries one, else as given (natural
    name order); and which: ``"timestamp"`` or ``"file name"``. O(n log n)."""
    names = [parse_vpr_name(f) for f in files]
    if names and all(n.timestamp is not None for n in names):
        order = sorted(range(len(files)),
                       key=lambda i: (names[i].timestamp, natural_key(files[i].name)))
        return [files[i] for i in order], "timestamp"
    return list(files), "file name"


def vpr_positions(files: list[Path]) -> Positions:
    """The names' positions as geographic :class:`Positions` (frames 0..n-1). O(n)."""
    names = [parse_vpr_name(f) for f in files]
    latlon = np.array([[n.lat, n.lon] for n in names], dtype=np.float64).reshape(-1, 2)
    stamps = np.array([np.nan if n.timestamp is None else n.timestamp for n in names])
    return Positions(np.arange(len(files), dtype=np.int64), latlon,
                     time=stamps if np.isfinite(stamps).any() else None, geographic=True)


@dataclass
class VprDataset:
    """A VPR-layout data set: the ordered database and query images with their UTM places.

    ``database_utm``/``queries_utm`` are ``(n, 2)`` eastings/northings in the zone of the
    first database image (names in another zone are reprojected through their lat/lon).
    """

    path: Path
    database: list[Path]
    queries: list[Path]
    database_order: str
    queries_order: str
    database_utm: Float64Array
    queries_utm: Float64Array
    zone: int
    south: bool

    @classmethod
    def open(cls, path: str | Path) -> VprDataset:
        """Open ``path`` (holding ``database/`` and ``queries/``, or ``images/test/...``).

        Raises
        ------
        InputError
            No such folders, a folder without images, or a name that is not a VPR name.
        """
        root = Path(path)
        for base in (root, root / "images" / "test"):
            if (base / "database").is_dir() and (base / "queries").is_dir():
                break
        else:
            raise InputError(f"{root}: not a VPR-layout data set (no database/ and queries/ "
                             "folders)")
        database, db_order = _ordered(list_images(base / "database"))
        queries, q_order = _ordered(list_images(base / "queries"))
        first = parse_vpr_name(database[0])
        return cls(root, database, queries, db_order, q_order,
                   _utm(database, first.zone, first.south),
                   _utm(queries, first.zone, first.south), first.zone, first.south)


def _ordered(files: list[Path]) -> tuple[list[Path], str]:
    """A folder of the data set in frame order, or InputError if it is not VPR-layout."""
    if not is_vpr_folder(files):
        other = next(f for f in files if not is_vpr_name(f.name))
        raise InputError(f"{other}: not a VPR-layout name ({_NAME_FORMAT})")
    return vpr_order(files)


def _utm(files: list[Path], zone: int, south: bool) -> Float64Array:
    from sprint_map.util.geo import GeoFrame

    names = [parse_vpr_name(f) for f in files]
    out = np.array([[n.east, n.north] for n in names], dtype=np.float64).reshape(-1, 2)
    other = np.array([n.zone != zone or n.south != south for n in names], dtype=bool)
    if other.any():
        lat = np.array([n.lat for n in names])[other]
        lon = np.array([n.lon for n in names])[other]
        out[other] = GeoFrame(zone, south).project(lat, lon)
    return out
