"""The writer lock: exclusive, non-blocking, and visible to a probing reader."""

from __future__ import annotations

import subprocess
import sys

import pytest

from sprint_map.errors import MapLockedError
from sprint_map.storage.lock import WriterLock, writer_active

HOLDER = """
import sys, time
from pathlib import Path
from sprint_map.storage.lock import WriterLock
WriterLock(Path(sys.argv[1])).acquire()
print("held", flush=True)
time.sleep(60)
"""


def test_no_lock_file_means_no_writer(tmp_path):
    assert not writer_active(tmp_path)


def test_a_released_lock_is_not_active(tmp_path):
    lock = WriterLock(tmp_path)
    lock.acquire()
    lock.release()
    assert not writer_active(tmp_path)


def test_a_writer_in_another_process_is_seen_and_refuses_a_second(tmp_path):
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(tmp_path)],
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        assert writer_active(tmp_path)
        with pytest.raises(MapLockedError, match=f"pid {holder.pid}"):
            WriterLock(tmp_path).acquire()
    finally:
        holder.kill()
        holder.wait()
    # The kernel drops a flock when its holder dies, even by SIGKILL.
    assert not writer_active(tmp_path)
    WriterLock(tmp_path).acquire()


def _unwritable(path):
    """Make ``path`` unwritable for this process: mode 0444, or for root (whom modes do not
    stop) the immutable attribute; return how to undo it (None: not possible here)."""
    import os

    if os.geteuid() != 0:
        path.chmod(0o444)
        return lambda: path.chmod(0o644)
    if subprocess.run(["chattr", "+i", str(path)], capture_output=True).returncode != 0:
        return None
    return lambda: subprocess.run(["chattr", "-i", str(path)], check=True)


def test_a_lock_file_this_process_cannot_write_is_the_permission_error(tmp_path):
    """Issue 14, item 15: a mode-0444 ``LOCK`` was an OS error (exit 1); it is the read-only
    map's error (exit 14), as for a map directory we cannot write, and readers still read."""
    from click.testing import CliRunner

    from sprint_map.cli.main import main
    from sprint_map.config import MapConfig
    from sprint_map.errors import ReadOnlyMapError
    from sprint_map.map import SprintMap

    with SprintMap.create(tmp_path / "m", MapConfig(dim=4)) as m:
        m.add_sequence([[1.0, 2, 3, 4]], name="a")
    lock_file = tmp_path / "m" / "LOCK"
    undo = _unwritable(lock_file)
    if undo is None:
        pytest.skip("running as root, and chattr +i failed: no way to make LOCK unwritable")
    try:
        with pytest.raises(ReadOnlyMapError, match=r"map is not writable \(.*LOCK: "):
            WriterLock(tmp_path / "m").acquire()
        result = CliRunner().invoke(main, ["remove", str(tmp_path / "m"), "a"])
        assert result.exit_code == ReadOnlyMapError.exit_code == 14, result.output
        assert result.output.startswith("Error: map is not writable (")
        assert len(result.output.strip().splitlines()) == 1
        result = CliRunner().invoke(main, ["sequences", str(tmp_path / "m")])
        assert result.exit_code == 0 and "a" in result.output
    finally:
        undo()
