"""Thumbnails: a small JPEG of each frame, for viewers (``ingest --thumbnails``).

A thumbnail is the frame scaled to :data:`THUMBNAIL_WIDTH` pixels wide (aspect kept, never
enlarged; ``cv2.INTER_AREA``) and encoded as a JPEG of quality :data:`THUMBNAIL_QUALITY`:
about 2 KiB for a street scene (1.9-2.5 KB on the synthetic city), kept in the map's LMDB with
the drive (:mod:`sprint_map.storage.thumbnails`). OpenCV is imported when the first thumbnail is made,
not with this module (the start-up rule: ``tests/test_startup.py``).

An image file is decoded twice when thumbnails are made: once to 8-bit gray for the descriptor,
exactly as without thumbnails (so ``--thumbnails`` never changes a descriptor), and once in
colour for the thumbnail, with the JPEG decoder's own downscaling (``IMREAD_REDUCED_COLOR_2/4/8``:
a quarter to a sixty-fourth of the pixels to decode) when the image is large enough for it.
"""

from __future__ import annotations

from typing import cast

import numpy as np
from numpy.typing import NDArray

from sprint_map.errors import InputError
from sprint_map.util.arrays import Image

#: Width of a thumbnail in pixels (its height follows the frame's aspect ratio).
THUMBNAIL_WIDTH = 96
#: JPEG quality of a thumbnail (OpenCV's 0-100 scale).
THUMBNAIL_QUALITY = 75
#: Tallest thumbnail in pixels: a very tall frame is scaled to fit (a JPEG holds at most 65,500
#: pixels a side, and the map at most 256 KiB a thumbnail); every frame makes one.
THUMBNAIL_MAX_HEIGHT = 4 * THUMBNAIL_WIDTH


def make_thumbnail(image: Image, width: int = THUMBNAIL_WIDTH,
                   quality: int = THUMBNAIL_QUALITY) -> bytes:
    """Encode ``image`` (gray, BGR or BGRA; uint8 or uint16) as a small JPEG.

    Returns
    -------
    bytes
        A baseline JPEG at most ``width`` pixels wide and :data:`THUMBNAIL_MAX_HEIGHT` tall
        (aspect kept but for a side of at least 1 pixel): any image the descriptor accepts
        makes one, so ``--thumbnails`` never changes which drives are accepted. O(pixels).
    """
    import cv2  # OpenCV loads with the first thumbnail made, not with the package

    if image.dtype == np.uint16:
        image = (cast("NDArray[np.uint16]", image) >> 8).astype(np.uint8)
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    height, wide = image.shape[:2]
    scale = min(1.0, width / wide, THUMBNAIL_MAX_HEIGHT / height)
    new_w = min(wide, max(1, round(wide * scale)))
    new_h = min(height, max(1, round(height * scale)))
    if (new_w, new_h) != (wide, height):
        image = cv2.resize(image, (new_w, new_h), interpolation=cv2.INTER_AREA)
    ok, buffer = cv2.imencode(".jpg", np.ascontiguousarray(image),
                              [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise InputError(f"cannot encode a {new_w}x{new_h} thumbnail")
    return bytes(buffer.tobytes())


def thumbnail_of_file(data: bytes, label: str, full_width: int, full_height: int,
                      width: int = THUMBNAIL_WIDTH) -> bytes:
    """The thumbnail of an encoded image file ``data`` already decoded (and so checked) once
    for its descriptor; ``full_width`` x ``full_height`` is its size in pixels.

    The colour decode lets the decoder downscale by the largest of 8, 4, 2 that keeps the
    image at least ``width`` pixels wide and as tall as the thumbnail will be (a reduced
    decode of a frame under 8 pixels tall would have no rows).
    """
    import cv2

    scale = min(1.0, width / full_width, THUMBNAIL_MAX_HEIGHT / full_height)
    out_h = max(1, round(full_height * scale))
    flags = cv2.IMREAD_COLOR
    for factor, reduced in ((8, cv2.IMREAD_REDUCED_COLOR_8), (4, cv2.IMREAD_REDUCED_COLOR_4),
                            (2, cv2.IMREAD_REDUCED_COLOR_2)):
        if full_width // factor >= width and full_height // factor >= out_h:
            flags = reduced
            break
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flags)
    if image is None or image.size == 0:
        raise InputError(f"{label}: cannot decode image in colour for its thumbnail")
    return make_thumbnail(image, width)


def decodes(data: bytes) -> bool:
    """Whether ``data`` decodes as an image (``check`` runs it on every thumbnail: a JPEG
    signature around garbage does not). Without OpenCV nothing can be decoded: True. O(pixels),
    ~0.1 ms for a 96 px thumbnail."""
    try:
        import cv2
    except ImportError:
        return True

    try:
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        return False
    return image is not None and image.size > 0


__all__ = ["THUMBNAIL_MAX_HEIGHT", "THUMBNAIL_QUALITY", "THUMBNAIL_WIDTH", "decodes",
           "make_thumbnail", "thumbnail_of_file"]
