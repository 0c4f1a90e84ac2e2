"""An encoded image's size from its header, read before anything is decoded.

A decompression bomb is small on the wire and huge decoded: a 415 KB PNG can declare 20000 x
20000 pixels (400 MB of gray, 1.2 GB of BGR). OpenCV has no header-only read, and its own limit
(``OPENCV_IO_MAX_IMAGE_PIXELS``, 2^30 by default) is read once per process, so
:func:`image_size` parses the few header bytes of the formats we read (PNG, JPEG, BMP, WebP,
TIFF) and :func:`check_pixels` refuses an image whose pixel count exceeds the limit before any
decoder allocates its buffer. Bytes whose format is none of those (or whose header is cut) are
refused too: their size cannot be known without decoding them.
"""

from __future__ import annotations

import struct
from typing import Any

from sprint_map.errors import InputError

__all__ = ["FORMATS", "HeaderError", "MAX_IMAGE_PIXELS", "check_pixels", "image_size"]

#: Largest image decoded by default (64 Mpx: 8192 x 8192; a 50 MP camera frame fits).
MAX_IMAGE_PIXELS = 1 << 26

#: The formats :func:`image_size` reads.
FORMATS = ("PNG", "JPEG", "BMP", "WebP", "TIFF")

_PNG = b"\x89PNG\r\n\x1a\n"
# JPEG start-of-frame markers (baseline, extended, progressive, lossless, ...): C0-CF but
# C4 (DHT), C8 (JPG extension) and CC (DAC).
_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
# Markers without a length field: TEM, RST0-7, SOI.
_STANDALONE = frozenset({0x01, *range(0xD0, 0xD9)})


class HeaderError(ValueError):
    """The bytes are not one of :data:`FORMATS`, or their header is cut or inconsistent."""


def image_size(data: bytes) -> tuple[str, int, int]:
    """``(format, width, height)`` of encoded image bytes, from the header alone.

    Raises
    ------
    HeaderError
        An unknown format, a cut header, or a header without a positive size.
    """
    head = bytes(data[:32])
    if head.startswith(_PNG):
        fmt, (width, height) = "PNG", _png(data)
    elif head.startswith(b"\xff\xd8"):
        fmt, (width, height) = "JPEG", _jpeg(data)
    elif head.startswith(b"BM"):
        fmt, (width, height) = "BMP", _bmp(data)
    elif head.startswith(b"RIFF") and head[8:12] == b"WEBP":
        fmt, (width, height) = "WebP", _webp(data)
    elif head[:4] in (b"II*\0", b"MM\0*", b"II+\0", b"MM\0+"):
        fmt, (width, height) = "TIFF", _tiff(data)
    else:
        raise HeaderError(f"not a {', '.join(FORMATS[:-1])} or {FORMATS[-1]} image")
    if width <= 0 or height <= 0:
        raise HeaderError(f"{fmt} header declares an empty image ({width} x {height})")
    return fmt, width, height


def check_pixels(data: bytes, label: str, max_pixels: int = MAX_IMAGE_PIXELS) -> None:
    """Refuse ``data`` unless its header declares at most ``max_pixels`` pixels.

    Raises
    ------
    InputError
        Naming ``label``: an unreadable header, or an image above the limit.
    """
    try:
        fmt, width, height = image_size(data)
    except HeaderError as exc:
        raise InputError(f"{label}: cannot decode image ({exc})") from None
    if width * height > max_pixels:
        raise InputError(f"{label}: {fmt} image of {width} x {height} pixels is larger than "
                         f"the limit of {max_pixels} pixels (refused before decoding)")


def _unpack(fmt: str, data: bytes, offset: int) -> tuple[Any, ...]:
    try:
        return struct.unpack_from(fmt, data, offset)
    except struct.error:
        raise HeaderError("the image header is cut short") from None


def _png(data: bytes) -> tuple[int, int]:
    # Signature, then the IHDR chunk first: length, "IHDR", width, height (big-endian).
    length, kind, width, height = _unpack(">I4sII", data, 8)
    if kind != b"IHDR" or length < 8:
        raise HeaderError("PNG without an IHDR chunk first")
    return width, height


def _jpeg(data: bytes) -> tuple[int, int]:
    # Walk the marker segments from SOI to the first start-of-frame; an EXIF thumbnail sits
    # inside an APPn segment and is skipped with it.
    i = 2
    while True:
        (byte,) = _unpack("B", data, i)
        if byte != 0xFF:
            raise HeaderError("JPEG marker expected")
        while True:  # fill bytes
            i += 1
            (marker,) = _unpack("B", data, i)
            if marker != 0xFF:
                break
        i += 1
        if marker in _STANDALONE:
            continue
        if marker in (0xD9, 0xDA):  # end of image, or a scan before any frame header
            raise HeaderError("JPEG without a frame header")
        (length,) = _unpack(">H", data, i)
        if marker in _SOF:
            height, width = _unpack(">xHH", data, i + 2)
            if height == 0:  # defined later by a DNL marker: not supported by libjpeg either
                raise HeaderError("JPEG whose height is given by a DNL marker")
            return width, height
        if length < 2:
            raise HeaderError("JPEG segment with a bad length")
        i += length


def _bmp(data: bytes) -> tuple[int, int]:
    (header,) = _unpack("<I", data, 14)
    if header == 12:  # BITMAPCOREHEADER: unsigned 16-bit sizes
        width, height = _unpack("<HH", data, 18)
        return width, height
    if header < 40:
        raise HeaderError("BMP with an unknown header")
    width, height = _unpack("<ii", data, 18)
    return width, abs(height)  # a negative height is a top-down bitmap


def _webp(data: bytes) -> tuple[int, int]:
    (chunk,) = _unpack("4s", data, 12)
    if chunk == b"VP8 ":  # lossy: a key frame's start code, then 14-bit sizes
        start, width, height = _unpack("<3sHH", data, 23)
        if start != b"\x9d\x01\x2a":
            raise HeaderError("WebP VP8 frame without a start code")
        return width & 0x3FFF, height & 0x3FFF
    if chunk == b"VP8L":  # lossless: signature 0x2f, then 14-bit width-1 and height-1
        signature, bits = _unpack("<BI", data, 20)
        if signature != 0x2F:
            raise HeaderError("WebP VP8L without its signature")
        return (bits & 0x3FFF) + 1, ((bits >> 14) & 0x3FFF) + 1
    if chunk == b"VP8X":  # extended: 24-bit canvas width-1 and height-1
        w0, w1, w2, h0, h1, h2 = _unpack("<6B", data, 24)
        return (w0 | w1 << 8 | w2 << 16) + 1, (h0 | h1 << 8 | h2 << 16) + 1
    raise HeaderError("WebP without a VP8, VP8L or VP8X chunk first")


def _tiff(data: bytes) -> tuple[int, int]:
    # The first image file directory (the page OpenCV decodes): ImageWidth (256) and
    # ImageLength (257), each a SHORT, LONG (or BigTIFF LONG8) value stored in the entry.
    e = "<" if data[:2] == b"II" else ">"
    big = data[2:4] in (b"+\0", b"\0+")
    if big:
        (offset,) = _unpack(e + "Q", data, 8)
        (count,) = _unpack(e + "Q", data, offset)
        entry, first, value_at = 20, offset + 8, 12
    else:
        (offset,) = _unpack(e + "I", data, 4)
        (count,) = _unpack(e + "H", data, offset)
        entry, first, value_at = 12, offset + 2, 8
    found: dict[int, int] = {}
    for k in range(min(count, 4096)):
        at = first + k * entry
        tag, kind = _unpack(e + "HH", data, at)
        if tag in (256, 257):
            if kind == 3:
                (found[tag],) = _unpack(e + "H", data, at + value_at)
            elif kind == 4:
                (found[tag],) = _unpack(e + "I", data, at + value_at)
            elif kind == 16 and big:
                (found[tag],) = _unpack(e + "Q", data, at + value_at)
            else:
                raise HeaderError("TIFF size of an unknown type")
        if len(found) == 2:
            return found[256], found[257]
    raise HeaderError("TIFF without ImageWidth and ImageLength")
