"""``check --repair``: rebuild what is derivable from the map's own data, report what is not.

LMDB's sequence records and edges and the shards' committed rows are the data; everything else
is derived from them and can be rebuilt (:data:`sprint_map.storage.check.REPAIRABLE`):

1. the writer's open removes leftover ``*.partial`` files, truncates the open shard and discards
   index files ahead of the map or torn (``MapStore._recover``);
2. every shard longer than its committed length is cut back (the bytes past it were never
   committed);
3. one LMDB write transaction rebuilds the broken derived records: the name and vertex-range
   indexes and sequence counters, the shard lengths, the reverse edge index and edge counter,
   and the union-find with its membership lists, totals and component counter; thumbnails
   that break their invariants are dropped (they are not derivable: the images are not kept);
4. if the persisted index is still unsound (or there is none: the open may have discarded a torn
   one), it is rebuilt from the shards and published atomically.

What is not derivable is reported, never guessed: sequence records that do not tile the vertex
ids, or a shard file missing or shorter than its committed rows (then nothing at all is touched,
not even by the writer's open: every derived record and file length depends on that tiling, and
no row is ever invented to fill a gap), an edge with an endpoint outside the map or inside
one sequence.

Every step is idempotent and leaves an openable map, so a kill anywhere (crash points
``repair.*``, and the ``recover.*`` and ``index.*`` ones on the way) is undone by running the
repair again.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

import lmdb

from sprint_map.storage.check import MapRecords, check_map, check_sequences, sequence_edges
from sprint_map.storage.drive_stats import drop_broken_stats
from sprint_map.storage.keys import EDGE_KEY, read_u64, u32, u64
from sprint_map.storage.records import RepairReport
from sprint_map.storage.sightings import drop_stray_sightings
from sprint_map.storage.store import MapStore
from sprint_map.storage.thumbnails import ThumbnailTest, drop_broken
from sprint_map.testing.crash import crash_point
from sprint_map.util.atomic import fsync_file, truncate

#: Areas rebuilt by the LMDB transaction of step 3.
RECORD_AREAS = ("lookup", "shard_lengths", "edge_index", "components", "removed", "thumbnails",
                "sightings", "drive_stats")


def repair_map(path: str | os.PathLike[str], *, seed: int = 0,
               check_config: Callable[[dict[str, Any]], object] | None = None,
               thumbnail_decodes: ThumbnailTest | None = None) -> RepairReport:
    """Repair the map at ``path`` as far as its own data allows, then check it.

    Takes the writer lock (``MapLockedError`` while another process writes). ``check_config``
    is called with the stored configuration record before anything is touched (see
    :meth:`MapStore.open <sprint_map.storage.store.MapStore.open>`).

    Notes
    -----
    O(sequences + edges + shards) LMDB work and ``stat`` calls, like ``check``; rebuilding the
    index, when needed, reads every shard row: O(vertices * dim).
    """
    report = RepairReport()
    # Even a writer's open truncates the open shard at next_vertex_id: first make sure the
    # records it trusts are sound (LMDB snapshots are consistent: no lock needed to read).
    with MapStore.open(path, readonly=True, check_config=check_config) as store:
        tiling = check_sequences(store)
        lost = [] if "sequences" in tiling.areas else lost_rows(store)
    if "sequences" in tiling.areas:
        report.found = tiling.violations
        report.skipped.append("nothing touched: the sequence records do not tile the vertex "
                              "ids, and every derived record and file length depends on them")
    elif lost:
        # Rows exist nowhere else: a writer's open, a truncation or an index rebuild would
        # only hide the loss (or fill it with zeros).
        report.found = lost
        report.skipped.append("nothing touched: shard files miss committed rows, which exist "
                              "nowhere else (restore the shard files from a backup, or "
                              "remove the sequences that lost rows)")
    else:
        with MapStore.open(path) as store:
            report.repaired.extend(store.recovery)
            before = check_map(store, seed=seed, thumbnail_decodes=thumbnail_decodes)
            report.found = before.violations
            total = store.counter("next_vertex_id")
            report.repaired.extend(truncate_shard_tails(store, total))
            crash_point("repair.shards_truncated")
            report.repaired.extend(rebuild_records(store, before.areas, thumbnail_decodes))
            crash_point("repair.committed")
            report.repaired.extend(_repair_index(store, total, before.areas, report.skipped))
    with MapStore.open(path, readonly=True) as store:
        report.after = check_map(store, seed=seed, thumbnail_decodes=thumbnail_decodes)
    return report


def lost_rows(store: MapStore) -> list[str]:
    """Shard files missing or shorter than their committed rows. O(shards) ``stat`` calls."""
    total = store.counter("next_vertex_id")
    problems = (store.shards.size_problem(shard, rows)
                for shard, rows in store.shards.lengths_for(total).items())
    return [problem for problem in problems if problem is not None]


def truncate_shard_tails(store: MapStore, total: int) -> list[str]:
    """Cut every shard file longer than its committed length back to it (fsynced).

    The writer's open does this for the open shard only (O(1)); here every shard is looked at.
    O(shards) ``stat`` calls.
    """
    shards = store.shards
    actions = []
    for shard, rows in shards.lengths_for(total).items():
        path = shards.path(shard)
        want = rows * shards.row_bytes
        if path.exists() and path.stat().st_size > want:
            truncate(path, want)
            fsync_file(path)
            actions.append(f"truncated {path.name} to {rows} committed rows")
    return actions


def rebuild_records(store: MapStore, areas: set[str],
                    thumbnail_decodes: ThumbnailTest | None = None) -> list[str]:
    """Rebuild the derived LMDB records of the broken ``areas`` in one write transaction.

    Notes
    -----
    O(sequences + edges) reads and puts, plus the union-find replay (see
    :meth:`sprint_map.storage.components.ComponentStore.rebuild`).
    """
    todo = [area for area in RECORD_AREAS if area in areas]
    if not todo:
        return []
    db = store.env.db

    def body(txn: lmdb.Transaction) -> list[str]:
        records = MapRecords.read(store, txn)
        meta, actions = db("meta"), []
        if "lookup" in todo:
            for name in ("seq_names", "vrange"):
                txn.drop(db(name), delete=False)
            for seq in records.seqs:
                store.put_lookups(txn, seq)
            next_seq = max([records.counters["next_seq_id"]] + [s.seq_id + 1 for s in records.seqs]
                           + [seq + 1 for _, _, seq in records.removed])
            txn.put(b"next_seq_id", u64(next_seq), db=meta)
            txn.put(b"n_sequences", u64(len(records.seqs)), db=meta)
            actions.append(f"rebuilt the name and vertex-range indexes of {len(records.seqs)} "
                           "sequences and their counters")
        if "shard_lengths" in todo:
            txn.drop(db("shards"), delete=False)
            lengths = store.shards.lengths_for(records.total)
            for shard, rows in lengths.items():
                txn.put(u32(shard), u64(rows), db=db("shards"))
            actions.append(f"rewrote the committed lengths of {len(lengths)} shards")
        if "edge_index" in todo:
            txn.drop(db("edges_rev"), delete=False)
            reverse = sorted(EDGE_KEY.pack(dst, src) for src, dst in records.edges)
            txn.cursor(db=db("edges_rev")).putmulti(((k, b"") for k in reverse), append=True)
            txn.put(b"n_edges", u64(len(records.edges)), db=meta)
            actions.append(f"rebuilt the reverse index of {len(records.edges)} edges")
        if "components" in todo:
            joins = [(a, b) for _, _, a, b in sequence_edges(records)]
            n = store.uf.rebuild(txn, {s.seq_id: s.length for s in records.seqs}, joins)
            txn.put(b"n_components", u64(n), db=meta)
            actions.append(f"rebuilt union-find and the member lists of {n} components from "
                           f"{len(joins)} edges")
        if "removed" in todo:
            cursor = txn.cursor(db=db("vertex_data"))
            for first, last in records.stray_positions:
                at = cursor.set_range(u64(first))
                while at and read_u64(cursor.key()) <= last:
                    cursor.delete()
                    at = bool(cursor.key())
            removed = sum(b - a + 1 for a, b, _ in records.removed)
            txn.put(b"removed_vertices", u64(removed), db=meta)
            actions.append(f"recounted {removed} removed vertices and dropped the positions of "
                           f"{len(records.stray_positions)} removed ranges")
        if "thumbnails" in todo:
            actions.extend(drop_broken(txn, store.env, {s.seq_id: s.length for s in records.seqs},
                                       thumbnail_decodes))
        if "sightings" in todo:
            actions.extend(drop_stray_sightings(
                txn, store.env, {s.seq_id: s.length for s in records.seqs}))
        if "drive_stats" in todo:
            dropped = drop_broken_stats(txn, store.env, (s.seq_id for s in records.seqs),
                                        store.config.dim)
            actions.append(f"dropped {dropped} broken drive statistics record(s): they exist "
                           "nowhere else (the drives' centring is unaffected)")
        crash_point("repair.before_commit")
        return actions

    return store.env.write(body)


def _repair_index(store: MapStore, total: int, areas: set[str], skipped: list[str]
                  ) -> list[str]:
    """Rebuild an unsound index (steps 2 and 3 change neither it nor any committed row), or
    write a missing one (none persisted yet, or the writer's open discarded a torn one)."""
    missing = "index" not in areas and total > 0 and not store.index.has_files()
    if "index" not in areas and not missing:
        return []
    if "shard_files" in areas:
        skipped.append("index not rebuilt: shard files are missing committed rows")
        return []
    store.index.rebuild(total, store.shards)
    verb = "wrote the missing" if missing else "rebuilt the"
    return [f"{verb} index from the shards ({total} vertices)"]


__all__ = ["rebuild_records", "repair_map", "truncate_shard_tails"]
