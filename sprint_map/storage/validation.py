"""Validation of what callers hand the store: descriptors and positions.

Bad input is refused with a specific error before anything is written.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sprint_map.errors import (
    DescriptorShapeError,
    EmptySequenceError,
    InputError,
    InvalidDescriptorError,
)


def validate_descriptors(descriptors: Any, dim: int, first_frame: int = 0) -> np.ndarray:
    """Return ``descriptors`` as a C-contiguous float32 (N, dim) array or raise a clear error."""
    arr = np.asarray(descriptors)
    if arr.dtype.kind not in "fiu":
        raise DescriptorShapeError(f"descriptors must be numeric, got dtype {arr.dtype}")
    if arr.ndim != 2:
        raise DescriptorShapeError(f"descriptors must be a 2-D array (N x {dim}), got {arr.shape}")
    if arr.shape[1] != dim:
        raise DescriptorShapeError(
            f"descriptor dimension {arr.shape[1]} does not match the map's dimension {dim}"
        )
    if arr.shape[0] == 0:
        raise EmptySequenceError("the sequence has no frames")
    with np.errstate(over="ignore"):  # values beyond float32 become Inf, refused just below
        arr = np.ascontiguousarray(arr, dtype=np.float32)
    if not np.isfinite(arr).all():
        bad = int(np.argmax(~np.isfinite(arr).all(axis=1)))
        raise InvalidDescriptorError(
            f"descriptor of frame {first_frame + bad} contains NaN or Inf"
        )
    return arr


def validate_positions(positions: Any, n: int) -> np.ndarray | None:
    """Positions as an (n, 4) float64 array ``x, y, heading_deg, timestamp`` (NaN if not given)."""
    if positions is None:
        return None
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[0] != n or not 2 <= pos.shape[1] <= 4:
        raise InputError(
            f"positions must be {n} rows of x, y[, heading[, time]], got shape {pos.shape}"
        )
    out = np.full((n, 4), np.nan)
    out[:, : pos.shape[1]] = pos
    if not np.isfinite(out[:, :2]).all():
        raise InputError("positions contain NaN or Inf in x or y")
    return out


#: Longest sequence name, in UTF-8 bytes.
MAX_NAME_BYTES = 500


def validate_name(name: str) -> None:
    """Refuse a sequence name that is empty, too long, or holds control characters.

    Names are unique within a map (checked by the writer) and printed one per line by the
    CLI, so a newline, a tab or any other non-printing character (but the space) is refused.
    """
    if not isinstance(name, str) or not name or len(name.encode()) > MAX_NAME_BYTES:
        raise InputError(f"sequence name must be 1 to {MAX_NAME_BYTES} bytes of text")
    if not name.isprintable():
        raise InputError(f"sequence name {name!r} contains non-printing characters")
