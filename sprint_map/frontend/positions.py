"""Reading per-frame positions (ground truth) from a CSV file.

Format: a header line naming the columns ``frame,x,y[,heading_deg][,sigma_m]`` (in any order,
names case-insensitive), then one row per frame of the source *before* any stride, frames
numbered from 0. ``x``/``y`` are metres in any fixed planar frame; ``heading_deg`` is the
direction of travel in degrees (any convention, as long as all traversals of a data set share
it); ``sigma_m`` the accuracy of a GNSS fix (one standard deviation, metres, > 0). A frame
without a row is a frame without a fix (NaN). Blank lines and lines starting with ``#`` are
skipped.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from sprint_map.errors import InputError
from sprint_map.util.arrays import Float64Array

__all__ = ["OPTIONAL_COLUMNS", "REQUIRED_COLUMNS", "gnss_fixes", "read_positions", "stored_form"]

REQUIRED_COLUMNS = ("frame", "x", "y")
OPTIONAL_COLUMNS = ("heading_deg", "sigma_m")
_EXPECTED = "frame,x,y[,heading_deg][,sigma_m]"


def read_positions(path: str | Path, n_frames: int | None, stride: int = 1) -> Float64Array:
    """Read the positions of the ``n_frames`` frames a source yielded.

    Parameters
    ----------
    path : str or Path
        The CSV file.
    n_frames : int or None
        Frames the source yielded (after ``stride``); ``None`` accepts any number of rows
        (frames ``0..M-1``), for a video whose length is unknown (``stride`` must then be 1).
    stride : int
        The source's stride: the CSV numbers the original frames, of which frames
        ``0, stride, 2*stride, ...`` were kept. A row for frame ``n_frames * stride`` or
        later describes a frame the drive does not have.

    Returns
    -------
    ndarray of float64, shape (n_frames, 3), (n_frames, 4) or (n_frames, 5)
        Columns ``frame, x, y[, heading_deg[, sigma_m]]`` for the kept frames, in frame order
        (``heading_deg`` NaN when only ``sigma_m`` is given); ``frame`` is the original frame
        number (``i * stride``); NaN ``x, y`` (and the rest) for a frame without a row.

    Raises
    ------
    InputError
        Missing or unreadable file, a bad header, a non-numeric or non-finite value, a
        ``sigma_m`` <= 0, a non-integer, negative or repeated frame number, a frame beyond the
        drive (a file longer than its drive), or no row. The message names the file and,
        where it applies, the line. O(rows).
    """
    path = Path(path)
    if (n_frames is not None and n_frames < 1) or stride < 1:
        raise ValueError("n_frames and stride must be >= 1")
    if n_frames is None and stride != 1:
        raise ValueError("stride needs n_frames")
    try:
        with path.open(newline="", encoding="utf-8") as handle:
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
    width_out = 5 if "sigma_m" in columns else 4 if "heading_deg" in columns else 3
    rows: dict[int, tuple[int, list[float]]] = {}  # frame -> (line number, [x, y, ...])
    for number, line in lines[1:]:
        fields = next(csv.reader([line]))
        if len(fields) != width:
            raise InputError(f"{path}:{number}: expected {width} fields, got {len(fields)}")
        values: dict[str, float] = {}
        for name, text in zip(columns, fields, strict=True):
            try:
                value = float(text)
            except ValueError:
                raise InputError(
                    f"{path}:{number}: {name} is not a number: {text.strip()!r}"
                ) from None
            if not math.isfinite(value):
                raise InputError(f"{path}:{number}: {name} is not finite: {text.strip()!r}")
            values[name] = value
        frame_value = values["frame"]
        if frame_value != int(frame_value) or frame_value < 0:
            raise InputError(f"{path}:{number}: frame must be a non-negative integer")
        frame = int(frame_value)
        if frame in rows:
            raise InputError(
                f"{path}:{number}: frame {frame} repeated (first on line {rows[frame][0]})"
            )
        if values.get("sigma_m", 1.0) <= 0:
            raise InputError(f"{path}:{number}: sigma_m must be > 0 metres, got "
                             f"{values['sigma_m']:g}")
        if n_frames is not None and frame >= n_frames * stride:
            raise InputError(
                f"{path}:{number}: frame {frame} is beyond the drive ({n_frames} frames"
                + (f" kept with stride {stride}" if stride > 1 else "") + "): a positions "
                "file longer than its drive"
            )
        data = [values["x"], values["y"], values.get("heading_deg", math.nan),
                values.get("sigma_m", math.nan)][:width_out - 1]
        rows[frame] = (number, data)

    if not rows:
        raise InputError(f"{path}: no position rows after the header")
    if n_frames is None:
        n_frames = max(rows) + 1
    out = np.full((n_frames, width_out), np.nan)
    out[:, 0] = np.arange(n_frames) * stride
    for i in range(n_frames):
        row = rows.get(i * stride)
        if row is not None:
            out[i, 1:] = row[1]
    return out


def stored_form(table: Float64Array) -> Float64Array:
    """Positions as a map stores them (``x, y, heading_deg``, NaN rows: no fix) from
    :func:`read_positions`' table. O(n)."""
    return table[:, 1:4]


def gnss_fixes(table: Float64Array) -> Float64Array:
    """A drive's GNSS fixes (``x, y[, sigma_m]``, NaN rows: no fix) from :func:`read_positions`'
    table. O(n)."""
    return table[:, [1, 2, 4]] if table.shape[1] > 4 else table[:, 1:3]


def _parse_header(path: Path, number: int, line: str) -> list[str]:
    names = [name.strip().lower() for name in next(csv.reader([line]))]
    known = set(REQUIRED_COLUMNS) | set(OPTIONAL_COLUMNS)
    unknown = [name for name in names if name not in known]
    missing = [name for name in REQUIRED_COLUMNS if name not in names]
    if unknown or missing or len(set(names)) != len(names):
        problem = (
            f"unknown column(s) {', '.join(repr(n) for n in unknown)}"
            if unknown
            else f"missing column(s) {', '.join(missing)}"
            if missing
            else "repeated column"
        )
        raise InputError(
            f"{path}:{number}: bad header ({problem}); expected {_EXPECTED}"
        )
    return names
