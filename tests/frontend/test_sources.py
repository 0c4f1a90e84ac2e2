"""Frame sources: image directories, videos and .npy files, streamed in parallel batches."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from sprint_map.errors import DescriptorShapeError, InputError, InvalidDescriptorError
from sprint_map.frontend import DescriptorSpec, open_source
from sprint_map.frontend.imagefiles import read_image
from tests.helpers.frames import frame, write_video

HOG = DescriptorSpec("hog")


@pytest.fixture
def image_dir(tmp_path) -> Path:
    """23 PNGs named without zero padding (natural order matters) plus a stray text file."""
    folder = tmp_path / "walk"
    folder.mkdir()
    for i in range(23):
        assert cv2.imwrite(str(folder / f"img{i}.png"), frame(i))
    (folder / "notes.txt").write_text("ignored")
    return folder


def expected_hog(folder: Path, count: int) -> np.ndarray:
    return np.stack([HOG.describe(read_image(folder / f"img{i}.png")) for i in range(count)])


@pytest.mark.parametrize(("workers", "executor"), [(1, "thread"), (2, "thread"), (3, "thread")])
@pytest.mark.parametrize("batch_size", [1, 5, 256])
def test_image_dir_batches_in_frame_order(image_dir, workers, executor, batch_size):
    source = open_source(image_dir, HOG, batch_size=batch_size, workers=workers, executor=executor)
    assert (source.kind, source.name, source.count, source.dim) == ("images", "walk", 23, 1764)
    batches = list(source.iter_batches())
    assert all(len(b) == batch_size for b in batches[:-1])
    assert 1 <= len(batches[-1]) <= batch_size
    assert all(b.dtype == np.float32 and b.flags.c_contiguous for b in batches)
    np.testing.assert_array_equal(np.concatenate(batches), expected_hog(image_dir, 23))


def test_process_pool_gives_the_same_descriptors(image_dir):
    source = open_source(image_dir, HOG, batch_size=8, workers=2, executor="process")
    np.testing.assert_array_equal(source.read_all(), expected_hog(image_dir, 23))


def test_stride_keeps_every_nth_frame(image_dir):
    source = open_source(image_dir, HOG, stride=5, workers=2)
    assert source.count == 5  # frames 0, 5, 10, 15, 20
    np.testing.assert_array_equal(source.read_all(), expected_hog(image_dir, 23)[::5])


def test_default_descriptor_is_hog_and_patchnorm_works(image_dir):
    assert open_source(image_dir, workers=1).spec == HOG
    spec = DescriptorSpec("patchnorm")
    out = open_source(image_dir, spec, workers=2).read_all()
    assert out.shape == (23, 512)
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, rtol=1e-5)


def test_progress_reports_frames_done_and_total(image_dir):
    calls: list[tuple[int, int | None]] = []
    source = open_source(
        image_dir, HOG, batch_size=10, workers=2, progress=lambda d, t: calls.append((d, t))
    )
    source.read_all()
    assert calls == [(10, 23), (20, 23), (23, 23)]
    override: list[tuple[int, int | None]] = []
    list(source.iter_batches(progress=lambda d, t: override.append((d, t))))
    assert override == [(10, 23), (20, 23), (23, 23)]


def test_consumer_may_stop_early(image_dir):
    source = open_source(image_dir, HOG, batch_size=4, workers=2)
    iterator = source.iter_batches()
    first = next(iterator)
    iterator.close()  # shuts the pool down; must not hang
    np.testing.assert_array_equal(first, expected_hog(image_dir, 4))


@pytest.mark.parametrize("workers", [1, 2])
def test_corrupt_image_fails_the_iteration_naming_the_file(image_dir, workers):
    bad = image_dir / "img7.png"
    bad.write_bytes(bad.read_bytes()[:100])
    source = open_source(image_dir, HOG, batch_size=4, workers=workers)
    with pytest.raises(InputError, match="img7.png"):
        source.read_all()


def test_non_image_with_image_extension_names_the_file(image_dir):
    (image_dir / "img30.jpg").write_text("this is not a JPEG")
    with pytest.raises(InputError, match="img30.jpg"):
        open_source(image_dir, HOG, workers=2).read_all()


def test_empty_directory_and_missing_path(tmp_path):
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="empty"):
        open_source(tmp_path / "empty")
    with pytest.raises(InputError, match="missing"):
        open_source(tmp_path / "missing")


def test_unsupported_file_type(tmp_path):
    path = tmp_path / "frames.txt"
    path.write_text("x")
    with pytest.raises(InputError, match="frames.txt"):
        open_source(path)


@pytest.mark.parametrize(
    "kwargs", [{"stride": 0}, {"batch_size": 0}, {"workers": 0}, {"executor": "gpu"}]
)
def test_invalid_options(image_dir, kwargs):
    with pytest.raises(ValueError):
        open_source(image_dir, **kwargs)


# --- video -----------------------------------------------------------------------------------


@pytest.mark.parametrize(("name", "fourcc"), [("drive.avi", "MJPG"), ("drive.mp4", "mp4v")])
@pytest.mark.parametrize("stride", [1, 3])
def test_video_frames_with_stride(tmp_path, name, fourcc, stride):
    decoded = write_video(tmp_path / name, 17, fourcc)
    assert len(decoded) == 17
    source = open_source(tmp_path / name, HOG, stride=stride, batch_size=4, workers=2)
    assert (source.kind, source.name, source.count) == ("video", "drive", None)
    assert source.estimated_count == len(decoded[::stride])  # type: ignore[attr-defined]
    calls: list[tuple[int, int | None]] = []
    out = source.read_all(progress=lambda d, t: calls.append((d, t)))
    np.testing.assert_array_equal(out, HOG.describe_batch(decoded[::stride]))
    assert calls[-1] == (len(decoded[::stride]), None)


def test_video_without_frames(tmp_path):
    write_video(tmp_path / "empty.avi", 0)
    with pytest.raises(InputError, match="empty.avi"):
        open_source(tmp_path / "empty.avi")


@pytest.mark.parametrize("content", [b"", b"not a video at all" * 100])
def test_corrupt_video(tmp_path, content):
    path = tmp_path / "broken.mp4"
    path.write_bytes(content)
    with pytest.raises(InputError, match="broken.mp4"):
        open_source(path)


# --- .npy ------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.float16])
def test_npy_streams_float32_batches(tmp_path, dtype):
    data = np.random.default_rng(0).normal(size=(50, 12)).astype(dtype)
    np.save(tmp_path / "run.npy", data)
    source = open_source(tmp_path / "run.npy", batch_size=16, stride=2)
    assert (source.kind, source.name, source.count, source.dim, source.spec) == (
        "npy",
        "run",
        25,
        12,
        None,
    )
    batches = list(source.iter_batches())
    assert [len(b) for b in batches] == [16, 9]
    assert all(b.dtype == np.float32 for b in batches)
    np.testing.assert_array_equal(np.concatenate(batches), data[::2].astype(np.float32))


@pytest.mark.parametrize(
    ("array", "error", "message"),
    [
        (np.zeros(10, np.float32), DescriptorShapeError, "2-D"),
        (np.zeros((2, 3, 4), np.float32), DescriptorShapeError, "2-D"),
        (np.zeros((5, 3), np.int64), DescriptorShapeError, "float"),
        (np.zeros((5, 3), bool), DescriptorShapeError, "float"),
        (np.zeros((0, 3), np.float32), InputError, "no descriptors"),
        (np.array([[0.0, 1.0], [np.nan, 2.0]], np.float32), InvalidDescriptorError, "row 1"),
        (np.array([[0.0, np.inf]], np.float64), InvalidDescriptorError, "row 0"),
    ],
    ids=["1-d", "3-d", "int", "bool", "empty", "nan", "inf"],
)
def test_bad_npy(tmp_path, array, error, message):
    path = tmp_path / "bad.npy"
    np.save(path, array)
    with pytest.raises(error, match=rf"bad\.npy.*{message}"):
        open_source(path)


def test_npy_that_is_not_an_array_file(tmp_path):
    path = tmp_path / "fake.npy"
    path.write_bytes(b"\x93NUMPY garbage")
    with pytest.raises(InputError, match="fake.npy"):
        open_source(path)
    np.save(tmp_path / "objects.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(InputError, match="objects.npy"):
        open_source(tmp_path / "objects.npy")


def test_npy_dimension_checked_against_spec(tmp_path):
    np.save(tmp_path / "d.npy", np.zeros((4, 100), np.float32))
    with pytest.raises(DescriptorShapeError, match="d.npy"):
        open_source(tmp_path / "d.npy", HOG)
    assert (
        open_source(
            tmp_path / "d.npy", DescriptorSpec("patchnorm", {"width": 10, "height": 10, "patch": 5})
        ).dim
        == 100
    )
