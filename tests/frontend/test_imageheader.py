"""Image sizes read from headers, and the pixel limit enforced before decoding (issue 14,
item 6: a 415 KB PNG of 20000 x 20000 pixels was decoded, 3.7 s and 400 MB, then described).
"""

from __future__ import annotations

import struct
import time
import zlib

import cv2
import numpy as np
import pytest

from sprint_map.errors import InputError
from sprint_map.frontend.imagefiles import decode_image, read_image
from sprint_map.frontend.imageheader import MAX_IMAGE_PIXELS, HeaderError, image_size


def bomb_png(width: int = 20000, height: int = 20000) -> bytes:
    """A valid 8-bit gray PNG of ``width x height`` black pixels, about 400 KB.

    Built in ~0.1 s without compressing 400 MB: after a full flush, deflate's output for the
    same input repeats byte for byte, so one compressed block of rows is repeated.
    """
    rows_per_block = 500
    assert height % rows_per_block == 0
    block = b"\0" * ((width + 1) * rows_per_block)  # filter byte 0 + pixels, per row
    c = zlib.compressobj(9)
    first = c.compress(block) + c.flush(zlib.Z_FULL_FLUSH)
    again = c.compress(block) + c.flush(zlib.Z_FULL_FLUSH)
    assert first[2:] == again  # (the first carries the 2-byte zlib header)
    adler = 1
    for _ in range(height // rows_per_block):
        adler = zlib.adler32(block, adler)
    idat = first + again * (height // rows_per_block - 1) + b"\x03\x00" + struct.pack(">I", adler)

    def chunk(kind: bytes, body: bytes) -> bytes:
        return (struct.pack(">I", len(body)) + kind + body
                + struct.pack(">I", zlib.crc32(kind + body)))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat)
            + chunk(b"IEND", b""))


def test_the_bomb_is_a_valid_png():
    small = bomb_png(600, 1000)  # the same construction, small enough to decode here
    image = cv2.imdecode(np.frombuffer(small, np.uint8), cv2.IMREAD_GRAYSCALE)
    assert image is not None and image.shape == (1000, 600) and not image.any()
    assert image_size(bomb_png()) == ("PNG", 20000, 20000)
    assert len(bomb_png()) < 500_000


def test_a_decompression_bomb_is_refused_before_decoding(tmp_path):
    bomb = bomb_png()
    start = time.perf_counter()
    with pytest.raises(InputError, match=r"bomb\.png: PNG image of 20000 x 20000 pixels is "
                       r"larger than the limit of 67108864 pixels \(refused before decoding\)"):
        decode_image(bomb, "bomb.png")
    (tmp_path / "bomb.png").write_bytes(bomb)  # files of ingest/localize: the same check
    with pytest.raises(InputError, match="20000 x 20000 pixels"):
        read_image(tmp_path / "bomb.png")
    assert time.perf_counter() - start < 0.5  # was 3.7 s (and 400 MB) per decode
    with pytest.raises(InputError, match="larger than the limit of 1000 pixels"):
        decode_image(bomb_png(600, 1000), max_pixels=1000)
    assert decode_image(bomb_png(600, 1000), max_pixels=600_000).shape == (1000, 600)


@pytest.mark.parametrize("ext", [".png", ".jpg", ".bmp", ".webp", ".tif"])
@pytest.mark.parametrize("shape", [(48, 64), (37, 129, 3), (1, 1)])
def test_sizes_from_headers_match_opencv(ext, shape, rng):
    image = rng.integers(0, 255, shape, dtype=np.uint8)
    data = cv2.imencode(ext, image)[1].tobytes()
    fmt, width, height = image_size(data)
    assert (height, width) == shape[:2]
    assert fmt == {".png": "PNG", ".jpg": "JPEG", ".bmp": "BMP", ".webp": "WebP",
                   ".tif": "TIFF"}[ext]
    assert decode_image(data, max_pixels=width * height).shape[:2] == shape[:2]


def test_other_webp_and_jpeg_headers(rng):
    image = rng.integers(0, 255, (50, 70, 3), dtype=np.uint8)
    lossless = cv2.imencode(".webp", image, [cv2.IMWRITE_WEBP_QUALITY, 101])[1].tobytes()
    assert lossless[12:16] == b"VP8L" and image_size(lossless) == ("WebP", 70, 50)
    progressive = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes()
    assert image_size(progressive) == ("JPEG", 70, 50)
    # An EXIF-like APP1 segment holding a thumbnail's own frame header comes first: skipped.
    thumb = cv2.imencode(".jpg", image[:8, :8])[1].tobytes()
    app1 = b"\xff\xe1" + struct.pack(">H", len(thumb) + 2) + thumb
    assert image_size(progressive[:2] + app1 + progressive[2:]) == ("JPEG", 70, 50)
    vp8x = b"RIFF\0\0\0\0WEBPVP8X" + b"\x0a\0\0\0" + b"\0" * 4 + b"\x1f\x4e\0" + b"\x1f\x4e\0"
    assert image_size(vp8x) == ("WebP", 20000, 20000)
    big_tiff = (b"II+\0" + struct.pack("<HHQ", 8, 0, 16) + struct.pack("<Q", 2)
                + struct.pack("<HHQQ", 256, 16, 1, 30000) + struct.pack("<HHQQ", 257, 4, 1, 9))
    assert image_size(big_tiff) == ("TIFF", 30000, 9)


@pytest.mark.parametrize("data", [
    b"not an image at all", b"P5\n20000 20000\n255\n", b"GIF89a\x20\x4e\x20\x4e",
    b"\x89PNG\r\n\x1a\n\0\0", b"\xff\xd8\xff\xe0\0\x10JFIF", b"\xff\xd8\xff\xda\0\x02",
    b"BM" + b"\0" * 12 + struct.pack("<I", 40) + struct.pack("<ii", 0, 5),
    b"RIFF\0\0\0\0WEBPVP8 \0\0\0\0\0\0\0\0\0\0\0\0\0\0", b"II*\0\x08\0\0\0\x00\x00",
])
def test_unknown_or_cut_headers_are_refused(data):
    with pytest.raises(HeaderError):
        image_size(data)
    with pytest.raises(InputError, match="^x.png: cannot decode image"):
        decode_image(data, "x.png")


def test_default_limit():
    assert MAX_IMAGE_PIXELS == 1 << 26
