"""Thumbnails never change which drives are accepted: tiny, flat and very long frames."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.frontend.thumbnails import (
    THUMBNAIL_MAX_HEIGHT,
    THUMBNAIL_WIDTH,
    make_thumbnail,
    thumbnail_of_file,
)

#: (height, width): under 8 px tall (a reduced decode has no rows), one pixel, very long both
#: ways (a JPEG holds at most 65,500 px a side), very tall (a thumbnail of megabytes).
SHAPES = [(7, 800), (1, 1), (3, 5), (1, 70_000), (70_000, 1), (30_000, 96), (5, 1_000)]


def _image(shape: tuple[int, int], seed: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (*shape, 3), dtype=np.uint8)


@pytest.mark.parametrize("ext", [".png", ".jpg"])
@pytest.mark.parametrize("shape", SHAPES)
def test_every_decodable_frame_makes_a_bounded_thumbnail(shape, ext):
    ok, buf = cv2.imencode(ext, _image(shape, 0))
    if not ok:
        pytest.skip(f"OpenCV cannot write a {shape} {ext}")
    thumb = thumbnail_of_file(buf.tobytes(), "frame", shape[1], shape[0])
    decoded = cv2.imdecode(np.frombuffer(thumb, np.uint8), cv2.IMREAD_COLOR)
    assert decoded is not None
    assert 1 <= decoded.shape[1] <= THUMBNAIL_WIDTH
    assert 1 <= decoded.shape[0] <= THUMBNAIL_MAX_HEIGHT
    assert len(thumb) < 256 * 1024
    assert make_thumbnail(_image(shape, 1))[:2] == b"\xff\xd8"


@pytest.mark.parametrize("shape", [(7, 800), (1, 70_000), (70_000, 1), (30_000, 96)])
def test_thumbnails_accept_what_the_descriptor_accepts(tmp_path, shape):
    """``ingest --thumbnails`` accepts a folder exactly when ``ingest`` does (was: an OpenCV
    traceback under 8 px tall, a refusal of very long frames)."""
    folder = tmp_path / "drive"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"{i:03d}.png"), _image(shape, i))
    codes = []
    for flag in ([], ["--thumbnails"]):
        map_path = tmp_path / f"m{len(codes)}.map"
        assert CliRunner().invoke(main, ["init", str(map_path), "--descriptor", "hog"]
                                  ).exit_code == 0
        result = CliRunner().invoke(main, ["ingest", str(map_path), str(folder), "-q", *flag])
        assert result.exception is None or isinstance(result.exception, SystemExit), \
            result.exception
        codes.append(result.exit_code)
    assert codes == [0, 0]
