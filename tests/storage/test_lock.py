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
