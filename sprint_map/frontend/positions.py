"""Reading per-frame positions (ground truth, GNSS fixes) from a CSV file.

Format: a header line naming the columns, in any order and case, one of

- ``frame,x,y[,heading_deg][,sigma_m]``: ``x``/``y`` metres in any fixed planar frame;
- ``frame,lat,lon[,heading_deg][,sigma_m]``: WGS84 latitude/longitude in degrees, which a map
  projects into the one UTM zone it stores (:class:`sprint_map.util.geo.GeoFrame`);

then one row per frame of the source *before* any stride, frames numbered from 0.
``heading_deg`` is the direction of travel in degrees (any convention, as long as all traversals
of a data set share it); ``sigma_m`` the fix's accuracy (one standard deviation, metres, > 0).
A frame without a row is a frame without a fix (its position is NaN). Blank lines and lines
starting with ``#`` are skipped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sprint_map.errors import InputError
from sprint_map.util.arrays import Float64Array
from sprint_map.util.geo import GeoFrame
from sprint_map.util.validation import regular_file

__all__ = ["MAX_FIELD_CHARS", "MAX_UNKNOWN_FRAMES", "OPTIONAL_COLUMNS", "Positions",
           "gnss_fixes", "read_positions"]

OPTIONAL_COLUMNS = ("heading_deg", "sigma_m")
_PLANAR, _GEOGRAPHIC = ("x", "y"), ("lat", "lon")
_EXPECTED = "frame,x,y[,heading_deg][,sigma_m] or frame,lat,lon[,heading_deg][,sigma_m]"
#: The longest field read (a number is a few dozen characters); longer: an error.
MAX_FIELD_CHARS = 1000
#: The most frames a file may number for a source of unknown length (a video: 3.8 days at
#: 30 fps; the result holds ~40 bytes per frame).
MAX_UNKNOWN_FRAMES = 10**7


@dataclass(frozen=True)
class Positions:
    """Per-frame positions of a drive's kept frames; NaN rows are frames without a fix.

    Attributes
    ----------
    frames : ndarray of int64, (n,)
        Original frame numbers (``i * stride``).
    xy : ndarray of float64, (n, 2)
        ``x, y`` metres, or ``lat, lon`` degrees when :attr:`geographic`.
    heading_deg, sigma_m, time : ndarray of float64, (n,), or None
        Heading, fix accuracy (metres) and time (seconds), None when the source has none.
    geographic : bool
        Whether :attr:`xy` holds latitude/longitude.
    """

    frames: np.ndarray
    xy: Float64Array
    heading_deg: Float64Array | None = None
    sigma_m: Float64Array | None = None
    time: Float64Array | None = None
    geographic: bool = False

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def fixed(self) -> np.ndarray:
        """(n,) bool: the frames with a fix."""
        return np.asarray(np.isfinite(self.xy).all(axis=1))

    def first_fix(self) -> tuple[float, float] | None:
        """``(lat, lon)`` (or ``(x, y)``) of the first frame with a fix, None without one."""
        idx = np.flatnonzero(self.fixed)
        return None if not len(idx) else (float(self.xy[idx[0], 0]), float(self.xy[idx[0], 1]))

    def metric(self, frame: GeoFrame | None) -> Positions:
        """These positions in metres: latitude/longitude projected into ``frame`` (required
        then); planar ones unchanged. O(n)."""
        if not self.geographic:
            return self
        if frame is None:
            raise ValueError("geographic positions need a GeoFrame")
        return Positions(self.frames, frame.project(self.xy[:, 0], self.xy[:, 1]),
                         self.heading_deg, self.sigma_m, self.time, geographic=False)

    def rows(self) -> Float64Array:
        """The stored form: ``(n, 5)`` ``x, y, heading_deg, time, sigma_m`` (NaN where
        unknown; x, y NaN for a frame without a fix). Metric positions only. O(n)."""
        if self.geographic:
            raise ValueError("project geographic positions first (Positions.metric)")
        out = np.full((len(self), 5), np.nan)
        out[:, :2] = self.xy
        for col, values in ((2, self.heading_deg), (3, self.time), (4, self.sigma_m)):
            if values is not None:
                out[:, col] = values
        return out

    def table(self) -> Float64Array:
        """``(n, 3 or 4)`` ``frame, x, y[, heading_deg]`` (ground truth's form). O(n)."""
        cols = [self.frames.astype(np.float64), self.xy[:, 0], self.xy[:, 1]]
        if self.heading_deg is not None:
            cols.append(self.heading_deg)
        return np.stack(cols, axis=1)

    def subset(self, keep: np.ndarray) -> Positions:
        """The rows ``keep`` (indices or a mask), frames renumbered as given. O(n)."""
        def pick(values: Float64Array | None) -> Float64Array | None:
            return None if values is None else values[keep]

        return Positions(self.frames[keep], self.xy[keep], pick(self.heading_deg),
                         pick(self.sigma_m), pick(self.time), self.geographic)


def read_positions(path: str | Path, n_frames: int | np.ndarray | None, stride: int = 1, *,
                   source_frames: int | None = None) -> Positions:
    """Read the positions of the frames a source yielded from the CSV ``path``.

    ``n_frames``: the frames the source yielded, as their count (after ``stride``: the kept
    frames are ``0, stride, 2*stride, ...`` of the source), as their source ordinals (an
    increasing array: the frames a bag's ``--every-m`` kept), or ``None`` (a video of unknown
    length, ``stride`` 1) for frames ``0..max frame`` (at most :data:`MAX_UNKNOWN_FRAMES`).
    The CSV numbers the source's frames, before any selection: ``source_frames`` of them
    (default: ``n_frames * stride``, or one past the last ordinal); a row for a frame at or
    beyond that is a file longer than its drive, an error. A file whose rows are exactly
    frames ``0..k-1`` for the ``k`` frames kept of a longer source numbers the kept frames,
    not the source's: an error too (taken as it is, each kept frame would get another's
    row). Returns one row per kept frame (``frames``: its source ordinal), NaN where the file
    has no row.

    Raises :class:`InputError`, one line naming the file (and the line): a missing or
    unreadable file, or one that is not a regular file; a bad header, a field that is not
    CSV or longer than :data:`MAX_FIELD_CHARS`, a non-numeric or non-finite value,
    ``sigma_m <= 0``, a latitude outside [-90, 90] or a longitude outside [-180, 180], a
    non-integer, negative or repeated frame number, a frame beyond the drive, rows numbering
    the kept frames, or no row at all. A UTF-8 byte-order mark is skipped. O(rows); memory
    O(file size + frames).
    """
    path = Path(path)
    if stride < 1:
        raise ValueError("stride must be >= 1")
    kept: np.ndarray | None
    if n_frames is None:
        if stride != 1 or source_frames is not None:
            raise ValueError("stride and source_frames need n_frames")
        kept, limit = None, MAX_UNKNOWN_FRAMES
    elif isinstance(n_frames, np.ndarray):
        kept = np.asarray(n_frames, dtype=np.int64)
        if stride != 1 or kept.ndim != 1 or not len(kept) or kept[0] < 0 \
                or np.any(np.diff(kept) <= 0):
            raise ValueError("source ordinals must be a non-empty increasing array, stride 1")
        limit = int(kept[-1]) + 1 if source_frames is None else source_frames
    else:
        if n_frames < 1:
            raise ValueError("n_frames must be >= 1")
        kept = np.arange(n_frames, dtype=np.int64) * stride
        limit = n_frames * stride if source_frames is None else source_frames
    if kept is not None and limit <= int(kept[-1]):
        raise ValueError("source_frames must exceed the last kept frame")
    columns, rows = _read_rows(path, limit, kept is not None, stride)
    if kept is None:
        kept = np.arange(max(rows) + 1, dtype=np.int64)
    elif len(kept) < limit and sorted(rows) == list(range(len(kept))) \
            and not np.array_equal(kept, np.arange(len(kept))):
        shown = ", ".join(str(f) for f in kept[:4].tolist()) + (", ..." if len(kept) > 4 else "")
        raise InputError(
            f"{path}: rows for frames 0..{len(kept) - 1}, one per kept frame, but a positions "
            f"file numbers the source's frames: {len(kept)} of its {limit} were kept (frames "
            f"{shown}); give one row per frame of the source")
    geographic = "lat" in columns
    first, second = _GEOGRAPHIC if geographic else _PLANAR
    n = len(kept)
    xy = np.full((n, 2), np.nan)
    optional = {name: np.full(n, np.nan) for name in OPTIONAL_COLUMNS if name in columns}
    for i, frame in enumerate(kept.tolist()):
        row = rows.get(frame)
        if row is None:
            continue
        values = row[1]
        xy[i] = values[first], values[second]
        for name, array in optional.items():
            array[i] = values[name]
    return Positions(kept, xy, optional.get("heading_deg"), optional.get("sigma_m"),
                     geographic=geographic)


def _read_rows(path: Path, limit: int, known: bool, stride: int
               ) -> tuple[list[str], dict[int, tuple[int, dict[str, float]]]]:
    """The header's columns and each frame's ``(line number, values)``, checked (see
    :func:`read_positions`); frames at or beyond ``limit`` are refused. O(rows)."""
    regular_file(path, "positions")
    try:
        with path.open(newline="", encoding="utf-8-sig") as handle:
            lines = [
                (number, line)
                for number, line in enumerate(handle, start=1)
                if line.strip() and not line.lstrip().startswith("#")
            ]
    except OSError as exc:
        raise InputError(f"{path}: cannot read positions ({exc.strerror or exc})") from exc
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not a UTF-8 text file") from exc
    if not lines:
        raise InputError(f"{path}: empty positions file (expected header {_EXPECTED})")

    columns = _parse_header(path, *lines[0])
    width = len(columns)
    rows: dict[int, tuple[int, dict[str, float]]] = {}  # frame -> (line number, values)
    for number, line in lines[1:]:
        fields = _fields(path, number, line)
        if len(fields) != width:
            raise InputError(f"{path}:{number}: expected {width} fields, got {len(fields)}")
        values: dict[str, float] = {}
        for name, text in zip(columns, fields, strict=True):
            try:
                value = float(text)
            except ValueError:
                raise InputError(
                    f"{path}:{number}: {name} is not a number: {text.strip()[:40]!r}"
                ) from None
            if not math.isfinite(value):
                raise InputError(f"{path}:{number}: {name} is not finite: {text.strip()!r}")
            values[name] = value
        _check_values(path, number, values)
        frame_value = values["frame"]
        if frame_value != int(frame_value) or frame_value < 0:
            raise InputError(f"{path}:{number}: frame must be a non-negative integer")
        frame = int(frame_value)
        if frame in rows:
            raise InputError(
                f"{path}:{number}: frame {frame} repeated (first on line {rows[frame][0]})"
            )
        if frame >= limit:
            if not known:
                raise InputError(f"{path}:{number}: frame {frame} is beyond the "
                                 f"{MAX_UNKNOWN_FRAMES} frames read for a drive of unknown "
                                 "length")
            raise InputError(
                f"{path}:{number}: frame {frame} is beyond the drive ("
                + (f"{-(-limit // stride)} frames kept with stride {stride}" if stride > 1
                   else f"{limit} frames") + "): a positions file longer than its drive"
            )
        rows[frame] = (number, values)
    if not rows:
        raise InputError(f"{path}: no position rows after the header")
    return columns, rows


def _fields(path: Path, number: int, line: str) -> list[str]:
    """The CSV fields of one line. Raises :class:`InputError` for a line that is not CSV
    (a stray or unterminated quote) or a field longer than :data:`MAX_FIELD_CHARS`."""
    import csv  # (here: the CLI loads this module for every command)

    if len(line) > MAX_FIELD_CHARS and max(map(len, line.split(","))) > MAX_FIELD_CHARS:
        raise InputError(f"{path}:{number}: a field longer than {MAX_FIELD_CHARS} characters")
    try:
        return next(csv.reader([line], strict=True), [])
    except csv.Error as exc:
        raise InputError(f"{path}:{number}: not a CSV line ({exc})") from None


def gnss_fixes(rows: Float64Array) -> Float64Array:
    """A drive's GNSS fixes ``(n, 3)`` ``x, y, sigma_m`` (NaN rows: no fix; NaN ``sigma_m``:
    the map's default accuracy) from its positions as a map stores them
    (:meth:`Positions.rows`, metric). O(n)."""
    return np.asarray(rows, dtype=np.float64)[:, [0, 1, 4]]


def _check_values(path: Path, number: int, values: dict[str, float]) -> None:
    sigma = values.get("sigma_m")
    if sigma is not None and sigma <= 0:
        raise InputError(f"{path}:{number}: sigma_m must be > 0 metres, got {sigma:g}")
    lat, lon = values.get("lat"), values.get("lon")
    if lat is not None and not -90 <= lat <= 90:
        raise InputError(f"{path}:{number}: lat {lat:g} is outside [-90, 90]")
    if lon is not None and not -180 <= lon <= 180:
        raise InputError(f"{path}:{number}: lon {lon:g} is outside [-180, 180]")


def _parse_header(path: Path, number: int, line: str) -> list[str]:
    names = [name.strip().lower() for name in _fields(path, number, line)]
    pair = _GEOGRAPHIC if "lat" in names or "lon" in names else _PLANAR
    required = ("frame", *pair)
    known = set(required) | set(OPTIONAL_COLUMNS)
    unknown = [name for name in names if name not in known]
    missing = [name for name in required if name not in names]
    if unknown or missing or len(set(names)) != len(names):
        problem = (
            f"unknown column(s) {', '.join(repr(n) for n in unknown)}"
            if unknown
            else f"missing column(s) {', '.join(missing)}"
            if missing
            else "repeated column"
        )
        raise InputError(f"{path}:{number}: bad header ({problem}); expected {_EXPECTED}")
    return names
