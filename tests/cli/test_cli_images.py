"""Images and video through the CLI: HoG maps, streaming ingest, bad files named and refused."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.errors import InputError


def run(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def frames(rng, n, shift=0.0):
    """A textured strip seen through a sliding window: consecutive frames overlap."""
    strip = cv2.GaussianBlur((rng.random((120, 40 * n + 200)) * 255).astype(np.uint8), (5, 5), 0)
    return [np.clip(strip[:, 40 * i: 40 * i + 160] * (1 - shift) + 40 * shift, 0, 255)
            .astype(np.uint8) for i in range(n)]


@pytest.fixture
def hog_map(tmp_path):
    path = tmp_path / "h.map"
    assert run("init", path, "--descriptor", "hog").exit_code == 0
    return path


def test_image_folder_and_video_ingest(tmp_path, rng, hog_map):
    images = frames(rng, 30)
    folder = tmp_path / "drive-a"
    folder.mkdir()
    for i, img in enumerate(images):  # natural order: img2 before img10
        cv2.imwrite(str(folder / f"img{i}.png"), img)
    result = run("ingest", hog_map, folder, "--json", "-q")
    assert result.exit_code == 0, result.output
    assert json.loads(result.output)["frames"] == 30

    video = tmp_path / "drive-b.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (160, 120), False)
    for img in images:
        writer.write(img)
    writer.release()
    result = run("ingest", hog_map, video, "--stride", 2, "--json", "-q")
    assert result.exit_code == 0, result.output
    out = json.loads(result.output)
    assert out["frames"] == 15 and out["name"] == "drive-b"
    matched = [d for d in out["decisions"] if d["seq_id"] == 0]
    # The video shows the same strip: most frames localise on the folder's drive at 2x speed.
    assert len(matched) >= 10
    assert np.mean([abs(d["image_id"] - 2 * d["frame"]) <= 2 for d in matched]) > 0.8
    assert run("check", hog_map).exit_code == 0


def test_truncated_image_is_named_and_nothing_is_committed(tmp_path, rng, hog_map):
    folder = tmp_path / "broken"
    folder.mkdir()
    for i, img in enumerate(frames(rng, 8)):
        cv2.imwrite(str(folder / f"{i:03d}.jpg"), img)
    data = (folder / "005.jpg").read_bytes()
    (folder / "005.jpg").write_bytes(data[: len(data) // 3])
    result = run("ingest", hog_map, folder, "-q")
    assert result.exit_code == InputError.exit_code
    assert "005.jpg" in result.output and result.output.startswith("Error: ")
    assert "Traceback" not in result.output
    info = json.loads(run("info", hog_map, "--json").output)
    assert (info["sequences"], info["vertices"]) == (0, 0)
    assert list((hog_map / "shards").iterdir()) == []


@pytest.mark.parametrize("kind", ["empty-dir", "not-an-image", "npy-wrong-dim"])
def test_bad_sources_fail_with_one_line(tmp_path, hog_map, kind):
    if kind == "empty-dir":
        source = tmp_path / "empty"
        source.mkdir()
    elif kind == "not-an-image":
        source = tmp_path / "notes.png"
        source.write_text("not a picture")
    else:
        source = tmp_path / "d.npy"
        np.save(source, np.zeros((3, 10), np.float32))
    result = run("ingest", hog_map, source, "-q")
    assert result.exit_code != 0
    assert len(result.output.strip().splitlines()) == 1 and result.output.startswith("Error: ")
    assert json.loads(run("info", hog_map, "--json").output)["vertices"] == 0


def test_ingest_thumbnails_kept_removed_and_compacted(tmp_path, rng, hog_map):
    """``ingest --thumbnails``: a small JPEG per frame (images and video), the descriptors the
    same as without; ``remove`` and ``compact`` take them along, ``check`` counts them."""
    from sprint_map.map import SprintMap

    images = frames(rng, 12)
    folder = tmp_path / "drive-a"
    folder.mkdir()
    for i, img in enumerate(images):
        cv2.imwrite(str(folder / f"{i:02d}.jpg"), cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    video = tmp_path / "drive-b.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (160, 120), False)
    for img in images:
        writer.write(img)
    writer.release()
    for source, extra in ((folder, ["--thumbnails"]), (video, ["--thumbnails"]),
                          (folder, ["--name", "plain"])):
        result = run("ingest", hog_map, source, "--no-merge", "-q", *extra)
        assert result.exit_code == 0, result.output
    with SprintMap.open(hog_map, readonly=True) as m:
        assert [m.thumbnail_count(s) for s in (0, 1, 2)] == [12, 12, 0]
        assert np.array_equal(m.descriptors(0), m.descriptors(2))  # thumbnails change nothing
        assert m.thumbnail(2, 0) is None
        for seq in (0, 1):
            thumb = cv2.imdecode(np.frombuffer(m.thumbnail(seq, 5), np.uint8), cv2.IMREAD_COLOR)
            assert thumb.shape == (72, 96, 3)  # 160x120 frames at 96 pixels wide
        assert m.check().checked["thumbnails"] == 24
    assert run("remove", hog_map, 0).exit_code == 0
    assert run("compact", hog_map).exit_code == 0
    result = run("check", hog_map, "--json")
    assert result.exit_code == 0, result.output
    assert json.loads(result.output)["checked"]["thumbnails"] == 12


def test_thumbnails_of_descriptors_are_refused(tmp_path, rng):
    path = tmp_path / "d.map"
    assert run("init", path, "--dim", 8).exit_code == 0
    np.save(tmp_path / "a.npy", rng.standard_normal((5, 8)).astype(np.float32))
    result = run("ingest", path, tmp_path / "a.npy", "--thumbnails")
    assert result.exit_code == InputError.exit_code
    assert result.output.startswith("Error: ") and "thumbnails need images or video" in result.output


@pytest.mark.parametrize("command", ["ingest", "localize"])
def test_images_of_several_sizes_in_one_drive_are_warned_about(tmp_path, rng, hog_map, command):
    """Two cameras in one folder: every frame is described (at the descriptor's size), and the
    user is told, once, which sizes and from which frame."""
    folder = tmp_path / "drive"
    folder.mkdir()
    for i, image in enumerate(frames(rng, 30)):
        if i >= 20:  # the second camera: another resolution
            image = cv2.resize(image, (320, 240))
        cv2.imwrite(str(folder / f"{i:03d}.png"), image)
    if command == "localize":
        assert run("ingest", hog_map, folder, "--name", "first", "-q").exit_code == 0
    result = CliRunner().invoke(main, [command, str(hog_map), str(folder), "-q"])
    assert result.exit_code == 0, result.output
    warnings = [line for line in result.stderr.splitlines() if line.startswith("Warning:")]
    assert len(warnings) == 1 and "images of 2 sizes in one drive" in warnings[0], warnings
    assert "160x120: 20 frame(s) from frame 0" in warnings[0]
    assert "320x240: 10 frame(s) from frame 20" in warnings[0]
    same = tmp_path / "same"
    same.mkdir()
    for i, image in enumerate(frames(rng, 5)):
        cv2.imwrite(str(same / f"{i:03d}.png"), image)
    assert "Warning" not in CliRunner().invoke(main, [command, str(hog_map), str(same),
                                                      "-q"]).stderr
