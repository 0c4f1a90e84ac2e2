"""Named crash points for crash-recovery tests.

Setting ``SPRINT_MAP_CRASH_AT=<name>`` makes the process SIGKILL itself when it reaches the
crash point of that name, so tests can kill a real writer at each step of the commit protocol.
Unset (the normal case) a crash point costs one dictionary look-up.
"""

from __future__ import annotations

import os
import signal

CRASH_ENV = "SPRINT_MAP_CRASH_AT"

#: Every crash point in the write paths, in commit-protocol order.
CRASH_POINTS = (
    "add.shards_written",  # descriptor rows written and fsynced, LMDB not yet committed
    "add.before_commit",  # inside the LMDB write transaction, before it commits
    "add.committed",  # LMDB committed, in-memory index not yet updated
    "index.partial_written",  # index file written to *.partial, not yet renamed
    "index.published",  # new index file renamed into place, older ones not yet removed
)


def crash_point(name: str) -> None:
    """SIGKILL this process if ``SPRINT_MAP_CRASH_AT`` names ``name``."""
    if os.environ.get(CRASH_ENV) == name:
        os.kill(os.getpid(), signal.SIGKILL)
