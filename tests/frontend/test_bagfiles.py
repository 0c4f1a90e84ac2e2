"""Opening a bag's files (issue 52, 10): regular files only, reads bounded by the file's size,
upper-case suffixes, compressed bags; every failure one ``BagReadError`` naming the bag."""

from __future__ import annotations

import os
import shutil
import struct
import subprocess
import sys
import tracemalloc

import numpy as np
import pytest

pytest.importorskip("rosbags")

from sprint_map.errors import InputError  # noqa: E402
from sprint_map.frontend.bagfiles import BagReadError  # noqa: E402
from sprint_map.frontend.descriptors import DescriptorSpec  # noqa: E402
from sprint_map.frontend.sources import open_source  # noqa: E402
from tests.helpers.bags import drive_spec, write_bag  # noqa: E402

HOG = DescriptorSpec("hog")
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"


def _cli(*args, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    """``sprint-map ARGS`` as a real process, killed (a failure, not a hung suite) after
    ``timeout`` seconds."""
    code = "import sys; from sprint_map.cli.main import main; main(sys.argv[1:], 'sprint-map')"
    return subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True,
                          text=True, timeout=timeout)


@pytest.fixture
def map_path(tmp_path):
    from click.testing import CliRunner

    from sprint_map.cli.main import main

    path = tmp_path / "m"
    assert CliRunner().invoke(main, ["init", str(path), "--descriptor", "hog"]).exit_code == 0
    return path


def _not_regular(tmp_path, what):
    if what == "fifo":
        os.mkfifo(tmp_path / "drive.bag")
        return tmp_path / "drive.bag"
    if what == "dev-zero":
        (tmp_path / "drive.mcap").symlink_to("/dev/zero")
        return tmp_path / "drive.mcap"
    folder = write_bag(tmp_path / "r2", "ros2-sqlite3", drive_spec(3))
    (db,) = folder.glob("*.db3")
    db.unlink()
    os.mkfifo(db)  # the storage file the metadata names
    return folder


@pytest.mark.parametrize("what", ["fifo", "dev-zero", "fifo-in-folder"])
def test_what_is_not_a_regular_file_is_refused_at_once(tmp_path, map_path, what):
    # (in real processes only: before, each blocked or read for ever)
    path = _not_regular(tmp_path, what)
    for command in ("ingest", "localize"):
        done = _cli(command, map_path, path, "--quiet", timeout=30)
        assert done.returncode == InputError.exit_code, done.stderr
        assert done.stderr.startswith(f"Error: {path}") and done.stderr.count("\n") == 1
        assert "must be a regular file, this is a" in done.stderr, done.stderr


def _first_record_length(path, length):
    """An MCAP whose first record (after the 8-byte magic and its opcode) says ``length``."""
    data = bytearray(path.read_bytes())
    data[9:17] = struct.pack("<Q", length)
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("length", [2**64 - 1, 2**62, 2**40, 2**31])
def test_a_length_beyond_the_file_allocates_nothing(tmp_path, length):
    path = write_bag(tmp_path / "d", "mcap", drive_spec(4))
    _first_record_length(path, length)
    size = path.stat().st_size
    tracemalloc.start()
    try:
        with pytest.raises(BagReadError) as info:  # before: OverflowError, MemoryError
            open_source(path, HOG)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert str(path) in str(info.value) and "\n" not in str(info.value)
    assert peak < 50 * size + (4 << 20), peak


def test_a_length_beyond_the_file_is_one_error_line(tmp_path, map_path):
    path = write_bag(tmp_path / "d", "mcap", drive_spec(4))
    _first_record_length(path, 2**64 - 1)
    done = _cli("ingest", map_path, path, "--quiet")
    assert done.returncode == InputError.exit_code and "Traceback" not in done.stderr
    assert done.stderr.startswith(f"Error: {path}: cannot read bag (") and \
        done.stderr.count("\n") == 1, done.stderr


@pytest.mark.parametrize(("kind", "suffix"), [("ros1", ".BAG"), ("mcap", ".MCAP"),
                                              ("mcap", ".Mcap")])
def test_upper_case_suffixes_are_read_as_the_bag_they_are(tmp_path, kind, suffix):
    path = write_bag(tmp_path / "d", kind, drive_spec(5))
    upper = path.with_name("DRIVE" + suffix)
    shutil.copy(path, upper)
    want = open_source(path, HOG)
    got = open_source(upper, HOG)  # before: "Unrecognized storage format '.BAG'"
    assert (got.kind, got.count, got.image_topic) == ("bag", 5, "/camera/image")
    np.testing.assert_array_equal(got.read_all(), want.read_all())
    np.testing.assert_array_equal(got.positions.xy, want.positions.xy)


COMPRESSED = [("ros2-sqlite3", "file"), ("ros2-sqlite3", "message"), ("ros2-mcap", "file"),
              ("ros2-mcap", "message"), ("ros2-mcap", "storage")]


@pytest.mark.parametrize(("kind", "mode"), COMPRESSED)
def test_compressed_bags_are_read_and_damaged_ones_are_one_error(tmp_path, kind, mode):
    plain = open_source(write_bag(tmp_path / "plain", kind, drive_spec(5)), HOG)
    folder = write_bag(tmp_path / "z", kind, drive_spec(5, compression=mode))
    np.testing.assert_allclose(open_source(folder, HOG).read_all(), plain.read_all(), atol=1e-6)
    (storage,) = (p for p in folder.iterdir() if p.name != "metadata.yaml")
    data = bytearray(storage.read_bytes())
    at = data.find(ZSTD_MAGIC)
    assert at >= 0
    data[at + 4:at + 12] = b"\xff" * 8  # a zstd frame header no decoder accepts
    storage.write_bytes(bytes(data))
    with pytest.raises(BagReadError) as info:  # before: ZstdError
        open_source(folder, HOG).read_all()
    assert str(folder) in str(info.value) and "Zstandard" in str(info.value)
