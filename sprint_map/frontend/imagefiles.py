"""Image files on disk: which files count as images, in which order, and decoding them.

Ordering is *natural*: digit runs compare as numbers, so ``img2.png`` comes before ``img10.png``
(plain string order would put ``img10`` first and scramble a sequence whose frame numbers are not
zero-padded). Ties are broken by the plain name, so the order is total and reproducible.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from sprint_map.errors import InputError
from sprint_map.frontend.imageheader import MAX_IMAGE_PIXELS, check_pixels
from sprint_map.util.arrays import Image

__all__ = ["IMAGE_EXTENSIONS", "VIDEO_EXTENSIONS", "decode_image", "is_image_name",
           "is_video_name", "list_images", "natural_key", "read_image", "read_image_bytes"]

#: File extensions read as images (compared case-insensitively).
IMAGE_EXTENSIONS = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp"})

#: File extensions treated as videos when a data-set traversal folder holds one.
VIDEO_EXTENSIONS = frozenset({".mp4", ".avi", ".mov", ".mkv", ".m4v", ".mpg", ".mpeg", ".webm"})

_DIGITS = re.compile(r"(\d+)")


def natural_key(name: str) -> tuple[tuple[tuple[int, int | str], ...], str]:
    """Sort key that orders digit runs numerically (``"img2" < "img10"``).

    Text runs compare case-insensitively; the raw name breaks ties (``"a01"`` vs ``"a1"``), so
    distinct names never compare equal.
    """
    parts: list[tuple[int, int | str]] = []
    for i, part in enumerate(_DIGITS.split(name)):
        if i % 2:
            parts.append((0, int(part)))
        elif part:
            parts.append((1, part.casefold()))
    return tuple(parts), name


def is_image_name(name: str) -> bool:
    """True if the file name has one of :data:`IMAGE_EXTENSIONS` (any case)."""
    return os.path.splitext(name)[1].lower() in IMAGE_EXTENSIONS


def is_video_name(name: str) -> bool:
    """True if the file name has one of :data:`VIDEO_EXTENSIONS` (any case)."""
    return os.path.splitext(name)[1].lower() in VIDEO_EXTENSIONS


def list_images(directory: Path) -> list[Path]:
    """Image files directly inside ``directory``, in natural order.

    Files with other extensions, hidden files (``.name``) and sub-directories are ignored; a
    dangling symbolic link with an image name is listed (reading it is an ``InputError``).

    Raises
    ------
    InputError
        If ``directory`` is missing, is not a directory, cannot be listed or holds no image.
    """
    directory = Path(directory)
    if not directory.exists():
        raise InputError(f"{directory}: no such file or directory")
    if not directory.is_dir():
        raise InputError(f"{directory}: not a directory")
    try:
        with os.scandir(directory) as entries:
            names = [
                e.name
                for e in entries
                if not e.name.startswith(".") and is_image_name(e.name)
                # A dangling link is a frame that cannot be read, not a file to skip silently.
                and (e.is_file() or (e.is_symlink() and not os.path.exists(e.path)))
            ]
    except OSError as exc:
        raise InputError(f"{directory}: cannot list directory ({exc.strerror or exc})") from exc
    if not names:
        extensions = "/".join(sorted(ext[1:] for ext in IMAGE_EXTENSIONS))
        raise InputError(f"{directory}: no image files ({extensions}) in directory")
    names.sort(key=natural_key)
    return [directory / name for name in names]


def read_image(path: Path, grayscale: bool = True, max_pixels: int = MAX_IMAGE_PIXELS
               ) -> Image:
    """Read and decode one image file: ``(H, W)`` uint8 if ``grayscale``, else ``(H, W, 3)`` BGR.

    ``grayscale`` decodes straight to 8-bit gray (``cv2.IMREAD_GRAYSCALE``: for JPEG, libjpeg
    skips the colour conversion, measurably faster than decoding BGR and converting);
    ``max_pixels`` is the largest image decoded, its size read from the header first
    (:func:`decode_image`).

    Raises :class:`InputError`, naming the file, if it cannot be read or decoded completely (a
    truncated JPEG or PNG is an error, not a silently grey-padded image) or is larger than
    ``max_pixels``. The bytes are read with Python and decoded with ``cv2.imdecode``, not
    ``cv2.imread``, which reports every failure as ``None`` and prints truncated-JPEG warnings
    without failing; ``imdecode`` releases the GIL, so threads decode in parallel.
    """
    return decode_image(read_image_bytes(path), str(path), grayscale, max_pixels)


def read_image_bytes(path: Path) -> bytes:
    """The bytes of image file ``path``; InputError (naming it) if it cannot be read."""
    try:
        return Path(path).read_bytes()
    except OSError as exc:
        raise InputError(f"{path}: cannot read image ({exc.strerror or exc})") from exc


def decode_image(data: bytes, label: str = "image", grayscale: bool = True,
                 max_pixels: int = MAX_IMAGE_PIXELS) -> Image:
    """Decode encoded image bytes (PNG, JPEG, BMP, WebP, TIFF) as :func:`read_image` does.

    ``label`` starts the error message (the file name, or what the bytes are). Raises
    ``InputError`` for empty, truncated or undecodable bytes, and, before any decoding, for
    an image whose header declares more than ``max_pixels`` pixels (a decompression bomb) or
    whose size cannot be read from its header
    (:func:`~sprint_map.frontend.imageheader.check_pixels`). Every image the service or
    ``ingest``/``localize`` decodes goes through here.
    """
    if not data:
        raise InputError(f"{label}: empty image file")
    check_pixels(data, label, max_pixels)
    if _is_truncated(data):
        raise InputError(f"{label}: truncated image file")
    import cv2  # OpenCV loads with the first image decoded, not with the package

    buffer = np.frombuffer(data, dtype=np.uint8)
    flags = cv2.IMREAD_GRAYSCALE if grayscale else cv2.IMREAD_COLOR
    try:
        image = cv2.imdecode(buffer, flags)
    except cv2.error as exc:  # some codecs raise instead of returning None
        raise InputError(
            f"{label}: cannot decode image ({str(exc).strip().splitlines()[-1]})"
        ) from exc
    if image is None or image.size == 0:
        raise InputError(f"{label}: cannot decode image (corrupt or not an image)")
    return image


def _is_truncated(data: bytes) -> bool:
    """True for a JPEG whose last scan is not followed by an end-of-image marker.

    OpenCV 4.14 refuses a cut JPEG itself, but older 4.x builds (still allowed by the
    dependency range) decode one cut anywhere after its header, padding it with grey and only
    printing "Premature end of JPEG file". The check is structural: the end-of-image marker
    ``FFD9`` must follow the last start-of-scan ``FFDA`` (entropy-coded data cannot contain
    either, thanks to byte stuffing; an EXIF thumbnail's own markers come before the main scan,
    and trailing bytes after the marker are allowed). Other formats' decoders fail by themselves.
    """
    if data[:3] != b"\xff\xd8\xff":
        return False
    last_scan = data.rfind(b"\xff\xda")
    return last_scan < 0 or data.find(b"\xff\xd9", last_scan) < 0
