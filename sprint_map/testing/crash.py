"""Named crash points for crash-recovery tests.

Setting ``SPRINT_MAP_CRASH_AT=<name>`` makes the process SIGKILL itself when it reaches the
crash point of that name, so tests can kill a real writer at each step of every write path.
Unset (the normal case) a crash point costs one dictionary look-up.
"""

from __future__ import annotations

import os
import signal

__all__ = ["ADD_POINTS", "SIGHTING_POINTS", "COMPACT_POINTS", "CRASH_ENV", "CRASH_POINTS", "GROUP_POINTS",
           "INDEX_POINTS", "JOIN_POINTS", "LEARN_POINTS", "RECOVER_POINTS", "REMOVE_POINTS", "REPAIR_POINTS", "SEGMENT_POINTS",
           "SUMMARIZE_POINTS", "UNMERGE_POINTS", "crash_point"]

CRASH_ENV = "SPRINT_MAP_CRASH_AT"

#: Adding a sequence (``add_sequence``, streamed ``ingest``, ``merge``), in commit order.
ADD_POINTS = (
    "add.shards_written",  # descriptor rows written and fsynced, LMDB not yet committed
    "add.thumbnails_written",  # inside the LMDB write transaction: thumbnails put, not committed
    "add.before_commit",  # inside the LMDB write transaction, before it commits
    "add.committed",  # LMDB committed, in-memory index not yet updated
)
#: A drive of a ``novel``-admission map that stored no frame: its sightings committed alone.
SIGHTING_POINTS = (
    "sightings.before_commit",  # inside the LMDB write transaction, before it commits
    "sightings.committed",  # committed, not yet returned
)
#: Several drives in one ingest (``SprintMap.ingest_drives``, ``sprint-map ingest A B ...``);
#: the last three are the group commit of appended drives (``storage/group_writer.py``).
GROUP_POINTS = (
    "group.between_drives",  # localised: a drive committed; appended: a drive's rows written
    "group.rows_written",  # every row of the group written and fsynced, no transaction yet
    "group.before_commit",  # inside the group's one LMDB transaction, every drive written
    "group.committed",  # the group's transaction committed, the index not yet caught up
)
#: ``join``: drives of another map copied in (``storage/join.py``, ``merge/join.py``); the
#: copy is one group commit, so the group's last three points fire inside a join too.
JOIN_POINTS = (
    "join.localised",  # every imported drive localised against the target, nothing written
    "join.records_copied",  # inside the group's transaction: per-drive records and edges put
    "join.committed",  # the join committed and its index caught up, not yet reported
)
#: Persisting the index (periodically while adding, on flush and close, in repair).
INDEX_POINTS = (
    "index.partial_written",  # index file written to *.partial, not yet renamed
    "index.published",  # new index file renamed into place, older ones not yet removed
)
#: The segmented index (training, sealing and merging segments; ``index --train``).
SEGMENT_POINTS = (
    "index.model_trained",  # model (and PCA) files published, no segment and no manifest yet
    "index.segment_written",  # a segment file published, the manifest naming it not yet
    "index.manifest_published",  # new manifest in place, files it no longer names not deleted
)
#: A writer's open bringing the files back to the committed state.
RECOVER_POINTS = (
    "recover.partials_removed",  # temp files removed, shard tail not yet truncated
    "recover.shards_truncated",  # shard tail truncated, stale index files not yet removed
)
#: ``check --repair`` (after the writer's open, so the recover points fire in it too).
REPAIR_POINTS = (
    "repair.shards_truncated",  # every shard cut to its committed length
    "repair.before_commit",  # inside the LMDB transaction rebuilding derived records
    "repair.committed",  # derived records committed, index not yet rebuilt
)

#: ``remove``: retiring sequences in one LMDB transaction.
REMOVE_POINTS = (
    "remove.before_commit",  # inside the LMDB transaction, everything written, not committed
    "remove.committed",  # committed, not yet returned
)
#: ``unmerge``: revoking one drive's edges in one LMDB transaction.
UNMERGE_POINTS = (
    "unmerge.before_commit",  # inside the LMDB transaction, edges revoked, components rebuilt
    "unmerge.committed",  # committed, not yet returned
)
#: ``compact``: a new generation built in a staging directory, then selected atomically.
COMPACT_POINTS = (
    "compact.staging_created",  # gen-N/ created, empty
    "compact.shards_written",  # live rows copied into gen-N/shards, fsynced
    "compact.lmdb_written",  # renumbered LMDB copied compacted into gen-N/map.lmdb, fsynced
    "compact.before_publish",  # gen-N complete with its index, CURRENT not yet replaced
    "compact.published",  # CURRENT names gen-N (the commit point), old generation still there
    "compact.old_partly_removed",  # part of the old generation deleted, the rest not yet
)
#: ``summarize``: the map without its redundant views, written like ``compact`` (a new
#: generation selected atomically; the old one is removed at ``compact.old_partly_removed``).
SUMMARIZE_POINTS = (
    "summarize.staging_created",  # gen-N/ created, empty
    "summarize.shards_written",  # kept rows copied into gen-N/shards, fsynced
    "summarize.lmdb_written",  # the summarised LMDB copied into gen-N/map.lmdb, fsynced
    "summarize.before_publish",  # gen-N complete with its index, CURRENT not yet replaced
    "summarize.published",  # CURRENT names gen-N (the commit point), old generation still there
)

#: ``index --learn`` / ``--no-learn`` and the writer's retraining after ``learn_every`` edges.
LEARN_POINTS = (
    "learn.projection_written",  # index/pG/projection.f32 published, no index, no pointer
    "learn.index_built",  # the index under the new projection (or none) built, no pointer
    "learn.published",  # learned.json names the new state (the commit point), old not deleted
)

#: Every crash point in the write paths.
CRASH_POINTS = (ADD_POINTS + SIGHTING_POINTS + GROUP_POINTS + INDEX_POINTS + SEGMENT_POINTS + RECOVER_POINTS + REPAIR_POINTS
                + REMOVE_POINTS + UNMERGE_POINTS + COMPACT_POINTS + SUMMARIZE_POINTS + LEARN_POINTS + JOIN_POINTS)


def crash_point(name: str) -> None:
    """SIGKILL this process if ``SPRINT_MAP_CRASH_AT`` names ``name``."""
    if os.environ.get(CRASH_ENV) == name:
        os.kill(os.getpid(), signal.SIGKILL)
