"""Frame payloads: a JSON descriptor or encoded image bytes, turned into one descriptor row.

Every problem is an :class:`ApiError` 4xx naming what is wrong (bad JSON, not an object, not a
list of numbers, wrong dimension, NaN/Inf, an image the map cannot describe or that does not
decode), never a 500.
"""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

from sprint_map import MAX_IMAGE_PIXELS, DescriptorSpec, describe_encoded
from sprint_map.errors import SprintMapError
from sprint_map.server.errors import ApiError, from_library
from sprint_map.util.arrays import Descriptors, DescriptorsLike
from sprint_map.util.validation import validate_descriptors, validate_name

__all__ = ["JSON_TYPES", "RAW_TYPE", "descriptor_from_image", "descriptor_from_json",
           "descriptor_from_raw", "media_type", "parse_json", "position_from_json", "session_name"]

JSON_TYPES = ("application/json",)
#: Raw little-endian float32 values, ``4 * dim`` bytes: no JSON parsing (~1 ms per HoG frame).
RAW_TYPE = "application/octet-stream"


def media_type(content_type: str | None) -> str:
    """The media type of a ``Content-Type`` header, lower case, without parameters."""
    return (content_type or "").split(";", 1)[0].strip().lower()


def parse_json(body: bytes) -> Any:
    """Parse a JSON body, or a 400 ``bad_json``."""
    try:
        return json.loads(body)
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError is a ValueError
        raise ApiError(400, "bad_json", f"the body is not valid JSON ({exc})") from None


def position_from_json(data: Any) -> tuple[float, ...] | None:
    """The optional ``"position": [x, y(, heading_deg)]`` of a JSON frame (finite numbers)."""
    if not isinstance(data, dict) or data.get("position") is None:
        return None
    value = data["position"]
    if (not isinstance(value, list) or not 2 <= len(value) <= 3
            or not all(type(v) is float or type(v) is int for v in value)):
        raise ApiError(422, "bad_payload", "position must be [x, y] or [x, y, heading_deg]")
    try:
        out = tuple(float(v) for v in value)
    except OverflowError:
        out = (math.inf,)
    if not all(math.isfinite(v) for v in out):
        raise ApiError(422, "bad_payload", "position must hold finite numbers")
    return out


def descriptor_from_json(data: Any, dim: int) -> Descriptors:
    """The ``(1, dim)`` float32 row of ``{"descriptor": [numbers]}``."""
    if not isinstance(data, dict) or "descriptor" not in data:
        raise ApiError(422, "bad_payload", 'expected a JSON object {"descriptor": [numbers]}')
    unknown = sorted(set(data) - {"descriptor", "position"})
    if unknown:
        raise ApiError(422, "bad_payload", f"unknown field(s) {', '.join(map(str, unknown))}")
    values = data["descriptor"]
    if not isinstance(values, list):
        raise ApiError(422, "bad_payload", "descriptor must be a list of numbers")
    # bool is an int subclass, but true is not a number here.
    if not all(type(v) is float or type(v) is int for v in values):
        raise ApiError(422, "bad_payload", "descriptor must be a list of numbers")
    if len(values) != dim:
        raise ApiError(422, "descriptor_shape",
                       f"descriptor has {len(values)} values, the map's dimension is {dim}")
    try:
        row = np.array([values], dtype=np.float64)
    except OverflowError:  # an integer beyond float64
        raise ApiError(422, "invalid_descriptor", "descriptor holds a number beyond float range"
                       ) from None
    return _validated(row, dim)


def descriptor_from_raw(body: bytes, dim: int) -> Descriptors:
    """The ``(1, dim)`` row of ``4 * dim`` bytes of little-endian float32."""
    if len(body) != 4 * dim:
        raise ApiError(422, "descriptor_shape", f"expected {4 * dim} bytes ({dim} little-endian "
                       f"float32), got {len(body)}")
    return _validated(np.frombuffer(body, dtype="<f4").reshape(1, dim), dim)


def descriptor_from_image(body: bytes, spec: DescriptorSpec | None, dim: int,
                          max_pixels: int = MAX_IMAGE_PIXELS) -> Descriptors:
    """Decode image bytes and describe them as the map's own images are described: through the
    one image path (:func:`~sprint_map.frontend.image_path.describe_encoded`), so a colour
    model's map decodes a posted frame in colour, as ``ingest`` does.

    An image whose header declares more than ``max_pixels`` pixels is refused (422
    ``bad_image``) before it is decoded.
    """
    if spec is None:
        raise ApiError(415, "images_not_supported",
                       f"this map holds precomputed descriptors (dim {dim}): send "
                       'application/json {"descriptor": [...]}, not an image')
    try:
        row = describe_encoded(spec, [(body, "image")], max_pixels)[0]
    except SprintMapError as exc:
        raise ApiError(422, "bad_image", str(exc)) from None
    except (ValueError, MemoryError) as exc:  # e.g. an image too large to decode
        raise ApiError(422, "bad_image", f"image: cannot describe it ({exc})") from None
    return _validated(row, dim)


def session_name(name: str | None) -> str | None:
    """A session's sequence name, checked by the store's one name check, or a 422 ``bad_input``.

    JSON can carry a lone surrogate (``"\\udcff"``): a Python ``str`` but not UTF-8 text, which
    :func:`~sprint_map.util.validation.validate_name` refuses (it was a 500).
    """
    if name is not None:
        try:
            validate_name(name)
        except SprintMapError as exc:
            raise from_library(exc) from None
    return name


def _validated(row: DescriptorsLike, dim: int) -> Descriptors:
    try:
        return validate_descriptors(row, dim)
    except SprintMapError as exc:
        raise from_library(exc) from None
