"""Reading per-frame positions (ground truth) from a CSV file.

Format: a header line naming the columns ``frame,x,y`` or ``frame,x,y,heading_deg`` (in any order,
names case-insensitive), then one row per frame of the source *before* any stride, frames
numbered from 0. ``x``/``y`` are metres in any fixed planar frame; ``heading_deg`` is the
direction of travel in degrees (any convention, as long as all traversals of a data set share
it). Blank lines and lines starting with ``#`` are skipped.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from sprint_map.errors import InputError
from sprint_map.util.arrays import Float64Array

__all__ = ["OPTIONAL_COLUMNS", "REQUIRED_COLUMNS", "read_positions"]

REQUIRED_COLUMNS = ("frame", "x", "y")
OPTIONAL_COLUMNS = ("heading_deg",)


def read_positions(path: str | Path, n_frames: int | None, stride: int = 1) -> Float64Array:
    """Read the positions of the ``n_frames`` frames a source yielded from the CSV ``path``.

    ``n_frames``: frames the source yielded (after ``stride``), or ``None`` to accept any number
    of rows (frames ``0..M-1``; a video of unknown length, ``stride`` 1). ``stride``: the
    source's; the CSV describes the original frames, of which ``0, stride, 2*stride, ...`` were
    kept, so it must hold between ``(n_frames - 1) * stride + 1`` and ``n_frames * stride`` rows
    (exactly ``n_frames`` with ``stride=1``).

    Returns float64 ``(n_frames, 3)`` or ``(n_frames, 4)``: columns ``frame, x, y[,
    heading_deg]`` of the kept frames in frame order, ``frame`` the original number
    (``i * stride``). Raises :class:`InputError`, naming the file and where it applies the line,
    on a missing or unreadable file, a bad header, a non-numeric or non-finite value, a
    non-integer, negative, repeated or missing frame number, or a frame count that does not
    match the source. O(rows).
    """
    import csv  # (here: the CLI loads this module for every command)

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
        raise InputError(f"{path}: empty positions file (expected header frame,x,y[,heading_deg])")

    columns = _parse_header(path, *lines[0])
    width = len(columns)
    rows: dict[int, tuple[int, list[float]]] = {}  # frame -> (line number, [x, y(, heading)])
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
        data = [values["x"], values["y"]]
        if "heading_deg" in values:
            data.append(values["heading_deg"])
        rows[frame] = (number, data)

    if not rows:
        raise InputError(f"{path}: no position rows after the header")
    if n_frames is None:
        n_frames = len(rows)
    low, high = (n_frames - 1) * stride + 1, n_frames * stride
    if not low <= len(rows) <= high:
        expected = str(n_frames) if stride == 1 else f"{low} to {high} (stride {stride})"
        raise InputError(
            f"{path}: {len(rows)} position rows for {n_frames} frames; expected {expected} rows"
        )
    beyond = [(number, frame) for frame, (number, _) in rows.items() if frame >= len(rows)]
    if beyond:
        # Unique frames, as many as rows, one too large: some frame below it is missing.
        missing = min(set(range(len(rows))) - rows.keys())
        number, frame = min(beyond)
        raise InputError(
            f"{path}:{number}: frame {frame} but frame {missing} is missing; "
            f"frames must be numbered 0..{len(rows) - 1} without gaps"
        )
    out = np.empty((n_frames, width), dtype=np.float64)
    for i in range(n_frames):
        out[i, 0] = i * stride
        out[i, 1:] = rows[i * stride][1]
    return out


def _parse_header(path: Path, number: int, line: str) -> list[str]:
    import csv

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
            f"{path}:{number}: bad header ({problem}); expected frame,x,y[,heading_deg]"
        )
    return names
