"""Image listing (natural order, extensions) and decoding with clear errors."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from sprint_map.errors import InputError
from sprint_map.frontend.imagefiles import list_images, natural_key, read_image


def write_image(path: Path, value: int = 100, size: tuple[int, int] = (48, 64)) -> Path:
    rng = np.random.default_rng(value)
    image = rng.integers(0, 256, size=(*size, 3), dtype=np.uint8)
    assert cv2.imwrite(str(path), image)
    return path


def test_natural_order():
    names = ["img10.png", "img2.png", "img1.png", "IMG3.png", "a.png", "img02.png"]
    assert sorted(names, key=natural_key) == [
        "a.png",
        "img1.png",
        "img02.png",
        "img2.png",
        "IMG3.png",
        "img10.png",
    ]


@given(st.lists(st.integers(0, 10**9), min_size=1, max_size=30, unique=True))
def test_natural_order_sorts_frame_numbers_numerically(numbers):
    names = [f"frame_{n}.jpg" for n in numbers]
    ordered = sorted(names, key=natural_key)
    assert ordered == [f"frame_{n}.jpg" for n in sorted(numbers)]


def test_list_images_filters_extensions_case_insensitively(tmp_path):
    for name in ["b10.PNG", "b2.jpg", "b3.JPEG", "b4.bmp", "b5.tif", "b6.TIFF", "b7.webp"]:
        write_image(tmp_path / name)
    (tmp_path / "notes.txt").write_text("not an image")
    (tmp_path / "positions.csv").write_text("frame,x,y\n")
    (tmp_path / ".hidden.png").write_bytes(b"")
    (tmp_path / "sub.png").mkdir()  # a directory with an image extension
    names = [p.name for p in list_images(tmp_path)]
    assert names == ["b2.jpg", "b3.JPEG", "b4.bmp", "b5.tif", "b6.TIFF", "b7.webp", "b10.PNG"]


def test_directory_without_images(tmp_path):
    (tmp_path / "readme.txt").write_text("x")
    with pytest.raises(InputError, match=str(tmp_path)):
        list_images(tmp_path)


def test_missing_directory(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        list_images(tmp_path / "nope")


@pytest.mark.parametrize("ext", [".png", ".jpg", ".bmp", ".tiff", ".webp"])
def test_read_image_decodes_to_gray_and_colour(tmp_path, ext):
    path = write_image(tmp_path / f"a{ext}")
    assert read_image(path).shape == (48, 64)
    assert read_image(path).dtype == np.uint8
    assert read_image(path, grayscale=False).shape == (48, 64, 3)


@pytest.mark.parametrize("ext", [".png", ".jpg", ".webp", ".bmp", ".tiff"])
@pytest.mark.parametrize("keep", [0.5, 0.95])
def test_truncated_image_is_an_error_naming_the_file(tmp_path, ext, keep):
    path = write_image(tmp_path / f"cut{ext}", size=(120, 160))
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])
    with pytest.raises(InputError, match=rf"cut{ext}"):
        read_image(path)


def test_jpeg_cut_just_before_its_end_marker(tmp_path):
    path = write_image(tmp_path / "a.jpg", size=(120, 160))
    path.write_bytes(path.read_bytes()[:-2])
    with pytest.raises(InputError, match="truncated"):
        read_image(path)


def test_jpeg_with_trailing_bytes_is_accepted(tmp_path):
    """Some cameras append data after the end-of-image marker; that is not truncation."""
    path = write_image(tmp_path / "a.jpg")
    path.write_bytes(path.read_bytes() + b"\x00" * 200)
    assert read_image(path).shape == (48, 64)


@pytest.mark.parametrize(
    "content", [b"", b"hello, I am a text file", b"\xff\xd8\xff" + b"\x00" * 50], ids=str
)
def test_non_image_content_is_an_error_naming_the_file(tmp_path, content):
    path = tmp_path / "bogus.png"
    path.write_bytes(content)
    with pytest.raises(InputError, match="bogus.png"):
        read_image(path)


def test_unreadable_file(tmp_path):
    with pytest.raises(InputError, match="gone.png"):
        read_image(tmp_path / "gone.png")
