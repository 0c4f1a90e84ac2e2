"""The map's input rules: descriptors, positions, sequence names, text and input files.

Bad input is refused with a specific error before anything is written. The store applies these
rules to everything it is handed; the service applies the same ones to a request before it
reaches the map (so both refuse the same input with the same message). Depends on nothing of
the package but its errors.
"""

from __future__ import annotations

import os
import stat
from typing import Any

import numpy as np

from sprint_map.errors import (
    DescriptorShapeError,
    EmptySequenceError,
    InputError,
    InvalidDescriptorError,
)
from sprint_map.util.arrays import Descriptors, Float64Array

__all__ = ["MAX_DESCRIPTOR_VALUE", "check_described", "decode_text", "descriptor_problem", "name_key",
           "parse_seq_ref", "regular_file", "shown", "validate_descriptors", "validate_name",
           "validate_positions"]

#: The largest magnitude of a descriptor element. A larger one is an overflow (of a model, of
#: a file's writer), not a descriptor: below it, the squared distances the index computes in
#: float32 stay finite for any dimension under 8e7 (``dim * (2e15)^2 < 3.4e38``), so a row
#: can neither overflow a distance nor be normalised to zero by an infinite norm.
MAX_DESCRIPTOR_VALUE = 1e15


def descriptor_problem(rows: Any) -> tuple[int, str] | None:
    """The first row of the 2-D ``rows`` that is not a descriptor, and why (``"element 3 is
    NaN"``): an element NaN, infinite or beyond :data:`MAX_DESCRIPTOR_VALUE`; None when every
    row is one. Checked on the raw values, before anything normalises them. O(rows * dim).
    """
    arr = np.asarray(rows)
    if arr.dtype.kind == "f" and float(np.finfo(arr.dtype).max) < MAX_DESCRIPTOR_VALUE:
        arr = arr.astype(np.float32)  # float16: the bound is no float16 (every value is below)
    with np.errstate(invalid="ignore"):
        ok = np.abs(arr) <= MAX_DESCRIPTOR_VALUE  # NaN compares False
    good = ok.all(axis=1)
    if good.all():
        return None
    row = int(np.argmin(good))
    col = int(np.argmin(ok[row]))
    value = float(arr[row, col])
    what = ("NaN" if np.isnan(value) else "infinite" if np.isinf(value)
            else f"{value:.3g}, beyond +-{MAX_DESCRIPTOR_VALUE:g} (an overflow, not a descriptor)")
    return row, f"element {col} is {what}"


def check_described(rows: Any, who: str, first: int = 0, count: int | None = None) -> None:
    """Refuse what a describer (``who``: "the model m.onnx", "hog") made of images
    ``first..``: the raw rows, before any normalisation; ``count`` the images it was given.

    Raises
    ------
    InvalidDescriptorError
        A row :func:`descriptor_problem` refuses; ``row`` and ``detail`` set for the frame
        source to name the frame.
    """
    problem = descriptor_problem(rows)
    if problem is None:
        return
    row, why = problem
    total = len(rows) if count is None else count
    exc = InvalidDescriptorError(f"{who} gave no descriptor for image {first + row} of {total} "
                                 f"({why})")
    exc.row, exc.detail = first + row, f"{who} gave no descriptor ({why})"
    raise exc


def validate_descriptors(descriptors: Any, dim: int, first_frame: int = 0) -> Descriptors:
    """Return ``descriptors`` as a C-contiguous float32 (N, dim) array or raise a clear error
    (:class:`InvalidDescriptorError` for a row :func:`descriptor_problem` refuses)."""
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
    problem = descriptor_problem(arr)
    if problem is not None:
        bad, why = problem
        kind = "contains NaN or Inf" if not np.isfinite(arr[bad]).all() else "is out of range"
        raise InvalidDescriptorError(f"descriptor of frame {first_frame + bad} {kind} ({why})")
    return arr


def validate_positions(positions: Any, n: int) -> Float64Array | None:
    """Positions as an (n, 5) float64 array ``x, y, heading_deg, timestamp, sigma_m`` (NaN
    where not given); a row whose ``x`` and ``y`` are both NaN is a frame without a fix (not
    stored). None when no frame has a fix. O(n).

    Raises
    ------
    InputError
        Not ``n`` rows of 2 to 5 columns; only one of ``x``, ``y`` NaN, or either infinite;
        a ``sigma_m`` that is not NaN or a finite value > 0.
    """
    if positions is None:
        return None
    pos = np.asarray(positions, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[0] != n or not 2 <= pos.shape[1] <= 5:
        raise InputError(
            f"positions must be {n} rows of x, y[, heading[, time[, sigma]]], got shape "
            f"{pos.shape}"
        )
    out = np.full((n, 5), np.nan)
    out[:, : pos.shape[1]] = pos
    missing = np.isnan(out[:, :2])
    if (missing[:, 0] != missing[:, 1]).any() or np.isinf(out[:, :2]).any():
        raise InputError("positions contain NaN or Inf in x or y (a frame without a fix has "
                         "both NaN)")
    sigma = out[:, 4]
    if not (np.isnan(sigma) | (np.isfinite(sigma) & (sigma > 0))).all():
        raise InputError("positions: sigma_m must be NaN or a finite value > 0 metres")
    if missing[:, 0].all():
        return None
    return out


#: Longest sequence name, in UTF-8 bytes.
MAX_NAME_BYTES = 500


def shown(text: str | bytes) -> str:
    """``text`` quoted for a one-line message, printable whatever it holds: undecodable bytes
    (as Python decodes file names and arguments, ``surrogateescape``) are shown as bytes."""
    if isinstance(text, bytes):
        return repr(text)
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        try:
            return repr(text.encode("utf-8", "surrogateescape"))
        except UnicodeEncodeError:  # a surrogate that no byte decoded to (e.g. from JSON)
            return ascii(text)
    return repr(text)


def decode_text(value: str | bytes, what: str, *, secret: bool = False) -> str:
    """``value`` as text, or :class:`InputError` (one line naming ``what``) if it is not UTF-8;
    the message quotes ``value`` unless it is a ``secret`` (a token).

    Every text a user or a file gives (names, paths, tokens) passes here once: ``bytes`` must
    decode as UTF-8; a ``str`` must encode as UTF-8, which a string decoded from other bytes
    does not (Python decodes arguments and file names with ``surrogateescape``: a byte 0xff
    becomes the lone surrogate U+DCFF), nor one with a lone surrogate from JSON.
    """
    refused = f"{what} is not UTF-8 text" if secret else f"{what} {shown(value)} is not UTF-8 text"
    if isinstance(value, bytes):
        try:
            return value.decode("utf-8")
        except UnicodeDecodeError:
            raise InputError(refused) from None
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:
        raise InputError(refused) from None
    return value


def validate_name(name: str) -> None:
    """Refuse a sequence name that is not UTF-8, empty, too long, or holds control characters.

    Names are unique within a map (checked by the writer), stored as UTF-8 and printed one per
    line by the CLI, so a newline, a tab or any other non-printing character (but the space) is
    refused. The one check of names for the store, the facade, the CLI and the service.
    """
    if not isinstance(name, str):
        raise InputError(f"sequence name must be text, got {type(name).__name__}")
    encoded = decode_text(name, "sequence name").encode("utf-8")
    if not name or len(encoded) > MAX_NAME_BYTES:
        raise InputError(f"sequence name must be 1 to {MAX_NAME_BYTES} bytes of text"
                         + (" (an empty name is not a name)" if not name else ""))
    if not name.isprintable():
        raise InputError(f"sequence name {name!r} contains non-printing characters")


def name_key(name: str) -> bytes | None:
    """The ``seq_names`` key to look ``name`` up by, or None if no sequence can have that name
    (empty, too long, not printable: a look-up then finds no sequence).

    Raises
    ------
    InputError
        ``name`` is not UTF-8 text.
    """
    if not isinstance(name, str):
        return None
    encoded = decode_text(name, "sequence name").encode("utf-8")
    if not name or len(encoded) > MAX_NAME_BYTES or not name.isprintable():
        return None
    return encoded


def parse_seq_ref(text: str, by_name: bool = False) -> int | str:
    """A sequence given on the command line: ASCII digits are an id, anything else a name.

    The one parser of SEQ arguments (``remove``, ``unmerge``, ``edges``). Only ``0``-``9``
    make an id: ``str.isdigit`` (and ``int``) also accept other scripts' digits, so a drive
    named ``１`` (a fullwidth one) would be read as sequence 1. With ``by_name`` the text is
    always a name. O(len(text)).
    """
    if by_name or not text or not text.isascii() or not text.isdigit():
        return text
    return int(text)


def regular_file(path: str | os.PathLike[str], what: str) -> int:
    """The size of the input file ``path``, which must be a regular file (after symbolic
    links): reading a FIFO would block forever, a device (a link to ``/dev/zero``) never end.
    O(1), one ``stat``.

    Raises
    ------
    InputError
        ``path`` is missing or unreadable, or a FIFO, a device, a socket or a directory;
        the message starts with ``path`` and names ``what`` it should be.
    """
    try:
        info = os.stat(path)
    except OSError as exc:
        raise InputError(f"{path}: cannot read {what} ({exc.strerror or exc})") from None
    if not stat.S_ISREG(info.st_mode):
        kind = next((name for test, name in (
            (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
            (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"),
            (stat.S_ISDIR, "a directory")) if test(info.st_mode)), "not a regular file")
        raise InputError(f"{path}: {what} must be a regular file, this is {kind}")
    return info.st_size
