"""Full consistency check of a map against every invariant of the on-disk format.

Run on a map opened read-only, so that nothing the writer's open would silently repair is hidden.
Every violation belongs to an *area* (:data:`sprint_map.storage.records.AREAS`); ``check --repair``
(:mod:`sprint_map.storage.repair`) rebuilds the areas that are derivable from the sequence
records, the edges and the shards (:data:`REPAIRABLE`) and reports the others.

Complexity: O(sequences + edges + shards) LMDB reads, plus one streaming pass over the shards
(every sequence's rows against the content digest committed with it), reading the persisted
index once and comparing **every** vector of the exact index with its shard row (in blocks of
``CHECK_BLOCK`` rows), or checksumming every file of the segmented index:
O(vertices * dim) in all.
"""

from __future__ import annotations

import hashlib
import struct
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import lmdb
import networkx as nx
import numpy as np

from sprint_map.errors import MapCorruptError, StorageIOError
from sprint_map.storage.components import MEMBER_KEY
from sprint_map.storage.drive_stats import check_drive_stats
from sprint_map.storage.generation import CURRENT_NAME, current_data, stale_generations
from sprint_map.storage.index.check import check_segments, has_segments
from sprint_map.storage.index.map_index import file_problem, index_files, projection_dirs
from sprint_map.storage.index.projection import LEARNED, Projection, read_learned
from sprint_map.storage.keys import (
    COMP_VAL,
    DIGEST_BYTES,
    EDGE_KEY,
    EDGE_VAL,
    NO_QUERY,
    REMOVED_VAL,
    UF_VAL,
    Raw,
    decode_text,
    read_u32,
    read_u64,
    u64,
)
from sprint_map.storage.lock import writer_active
from sprint_map.storage.provenance import ADDED_BY_AT
from sprint_map.storage.records import CheckReport, SequenceRecord
from sprint_map.storage.sightings import scan_sightings
from sprint_map.storage.store import COUNTERS, INDEX_DIR, SHARDS_DIR, MapStore
from sprint_map.storage.thumbnails import ThumbnailTest, scan_thumbnails
from sprint_map.util.atomic import PARTIAL_SUFFIX
from sprint_map.util.lazy import faiss  # imported on first use

__all__ = ["CHECK_BLOCK", "MALFORMED", "MapRecords", "REPAIRABLE", "check_digests", "check_index",
           "check_map", "check_sequences", "check_shards", "check_sightings", "check_thumbnails", "edge_added_by",
           "partial_files", "sequence_edges", "vertex_owner"]

#: Rows compared (index vectors with shard rows) or hashed per block: bounds check's memory.
CHECK_BLOCK = 65536

#: :attr:`MapRecords.added_by` of an edge whose value is not an edge value.
MALFORMED = -1

#: Areas ``check --repair`` rebuilds: everything derivable from the sequence records, the edges
#: and the shards. The others hold information that exists nowhere else. Thumbnails are not
#: derivable either (the images are not kept), but they are only a view: the repair drops the
#: ones that break the invariants, and says so.
REPAIRABLE = frozenset({"lookup", "shard_lengths", "edge_index", "components", "index", "temp",
                        "removed", "thumbnails", "sightings", "drive_stats"})


@dataclass
class MapRecords:
    """Every LMDB record the check reads, from one snapshot. O(sequences + edges) memory."""

    counters: dict[str, int]
    seqs: list[SequenceRecord]
    names: dict[str, int]
    vrange: dict[int, int]
    shard_rows: dict[int, int]
    edges: list[tuple[int, int]]
    rev: list[tuple[int, int]]
    uf: dict[int, tuple[int, int]]
    members: list[tuple[int, int]]
    comp: dict[int, tuple[int, int]]
    #: removed vertex ranges ``(first, last, seq_id)`` (schema 2) and their counter
    removed: list[tuple[int, int, int]] = field(default_factory=list)
    removed_vertices: int = 0
    #: removed ranges that still hold a position (``vertex_data`` key): one seek per range
    stray_positions: list[tuple[int, int]] = field(default_factory=list)
    #: provenance of each edge, parallel to ``edges``: the sequence that added it, ``NO_QUERY``
    #: for none, ``MALFORMED`` for a value that is not an edge value
    added_by: list[int] = field(default_factory=list)
    #: content digests of the sequences' rows (``digests``; a sequence written before digests
    #: has none)
    digests: dict[int, bytes] = field(default_factory=dict)

    @classmethod
    def read(cls, store: MapStore, txn: lmdb.Transaction) -> MapRecords:
        env = store.env

        def keys(name: str, key: struct.Struct) -> list[tuple[int, int]]:
            return [key.unpack(k) for k in txn.cursor(db=env.db(name)).iternext(values=False)]

        removed = [(REMOVED_VAL.unpack(v)[0], read_u64(k), REMOVED_VAL.unpack(v)[1])
                   for k, v in txn.cursor(db=env.db("removed"))] if env.has_db("removed") else []
        positions = env.db("vertex_data")
        edges = [(EDGE_KEY.unpack(k), edge_added_by(v))
                 for k, v in txn.cursor(db=env.db("edges"))]

        return cls(
            counters={name: store.counter(name, txn) for name in COUNTERS},
            seqs=[SequenceRecord.decode(v) for _, v in txn.cursor(db=env.db("sequences"))],
            names={decode_text(k, "name"): read_u32(v)
                   for k, v in txn.cursor(db=env.db("seq_names"))},
            vrange={read_u64(k): read_u32(v) for k, v in txn.cursor(db=env.db("vrange"))},
            shard_rows={read_u32(k): read_u64(v) for k, v in txn.cursor(db=env.db("shards"))},
            edges=[key for key, _ in edges],
            rev=keys("edges_rev", EDGE_KEY),
            uf={read_u32(k): UF_VAL.unpack(v) for k, v in txn.cursor(db=env.db("uf"))},
            members=keys("members", MEMBER_KEY),
            comp={read_u32(k): COMP_VAL.unpack(v) for k, v in txn.cursor(db=env.db("comp"))},
            removed=removed,
            removed_vertices=store.removed_vertices(txn),
            stray_positions=[(a, b) for a, b, _ in removed if _any_key(txn, positions, a, b)],
            added_by=[added for _, added in edges],
            digests={read_u32(k): bytes(v) for k, v in txn.cursor(db=env.db("digests"))}
            if env.has_db("digests") else {},
        )

    @property
    def total(self) -> int:
        return self.counters["next_vertex_id"]


def _any_key(txn: lmdb.Transaction, db: Any, first: int, last: int) -> bool:
    """Whether ``db`` (``>Q`` keys) has a key in ``first..last``. One seek."""
    cursor = txn.cursor(db=db)
    return bool(cursor.set_range(u64(first))) and read_u64(cursor.key()) <= last


def vertex_owner(seqs: list[SequenceRecord], total: int) -> Callable[[int], int | None]:
    """``vertex -> seq_id`` by bisection over the sequences' first vertices (None if outside).

    A vertex in a removed range (between live sequences) has no owner either.

    Notes
    -----
    O(n log n) to build, O(log n) per call; meaningful when the sequences tile ``0..total-1``.
    """
    ordered = sorted(seqs, key=lambda s: s.first_vertex)
    starts = np.array([s.first_vertex for s in ordered], dtype=np.int64)
    ids = [s.seq_id for s in ordered]
    lasts = [s.last_vertex for s in ordered]

    def owner(vid: int) -> int | None:
        if not 0 <= vid < total or not len(starts):
            return None
        at = int(np.searchsorted(starts, vid, side="right")) - 1
        return ids[at] if at >= 0 and vid <= lasts[at] else None

    return owner


def sequence_edges(records: MapRecords, report: CheckReport | None = None
                   ) -> list[tuple[int, int, int, int]]:
    """Edges as ``(src, dst, src_seq, dst_seq)``, leaving out (and reporting) invalid ones.

    An edge is invalid if an endpoint lies outside the map or both lie in one sequence. These
    are the edges that define the components. O(E log n).
    """
    owner = vertex_owner(records.seqs, records.total)
    out = []
    for src, dst in records.edges:
        a, b = owner(src), owner(dst)
        if a is None or b is None:
            if report is None:
                continue
            if all(0 <= v < records.total for v in (src, dst)):
                report.violation("edges", f"edge {src} -> {dst} has an endpoint in a removed "
                                          "vertex range")
            else:
                report.violation("edges", f"edge {src} -> {dst} has an endpoint outside the "
                                          f"map's {records.total} vertices")
        elif a == b:
            if report is not None:
                report.violation("edges", f"edge {src} -> {dst} lies inside sequence {a}")
        else:
            out.append((src, dst, a, b))
    return out


def check_map(store: MapStore, *, seed: int = 0,
              thumbnail_decodes: ThumbnailTest | None = None) -> CheckReport:
    """Verify every invariant of ``store``; see ``docs/architecture.md``, "Invariants".
    ``thumbnail_decodes`` (the facade's: an image decoder) is run on every thumbnail."""
    report = CheckReport()
    with store.env.read() as txn:  # one snapshot: a live writer's later drive is not a stray
        records = MapRecords.read(store, txn)
        stats, problems = check_drive_stats(txn, store.env, (s.seq_id for s in records.seqs),
                                            store.config.dim)
    report.checked.update(sequences=len(records.seqs), vertices=records.total,
                          edges=len(records.edges))
    _check_sequences(records, report)
    check_shards(store, records.total, report)
    if "sequences" not in report.areas and "shard_files" not in report.areas:
        check_digests(store, records, report)
    if records.shard_rows != store.shards.lengths_for(records.total):
        report.violation("shard_lengths", f"shard lengths in LMDB {records.shard_rows} do not "
                                          f"match {records.total} vertices")
    report.checked["shards"] = len(records.shard_rows)
    _check_edges(records, report)
    _check_provenance(records, report)
    _check_components(records, sequence_edges(records, report), report)
    check_thumbnails(store, records, report, thumbnail_decodes)
    check_sightings(store, records, report)
    for problem in problems:
        report.violation("drive_stats", problem)
    report.checked["drive_stats"] = stats
    # Beside a live writer, index files it publishes after our snapshot (its temp file, a file
    # ahead of the snapshot, an older file it removes) are in flight, not faults of the map.
    live = store.readonly and writer_active(store.path)
    if live:
        report.notes.append("a writer holds the map's LOCK: index files in flight are notes")
    check_index(store, records.total, report, seed, live=live)
    live_data = current_data(store.path)
    if live_data != store.data_path:  # this store was opened before a compaction
        report.notes.append(f"checked the generation this process opened ({store.data_path.name}"
                            f"); the map was compacted since into {live_data.name}")
    for stale in stale_generations(store.path, live_data):
        name = "generation 0 (top level)" if stale == store.path else stale.name
        report.notes.append(f"{name} is not the live generation (a reader may still have it "
                            "open, or a compaction was interrupted): removed by the next "
                            "writer's open")
    check_partials(store, live, report)
    return report


def check_partials(store: MapStore, live: bool, report: CheckReport) -> None:
    """Leftover ``*.partial`` files (area ``temp``): a regular file is the temp file of an
    interrupted atomic publication (a kill between its write and its rename: the map is whole,
    no reader ever opens it, the next writer's open removes it), so a note; anything else of
    that name (a directory, a link, a device) no writer made and the next writer's open cannot
    remove: a violation. O(entries of the map's directories)."""
    for entry in partial_files(store):
        message = f"leftover temp file {entry.relative_to(store.path)}"
        if entry.is_symlink() or not entry.is_file():
            report.violation("temp", f"{message} is not a regular file (no writer leaves one)")
        elif live and INDEX_DIR in (entry.parent.name, entry.parent.parent.name):
            report.notes.append(f"{message} (being written by the live writer)")
        elif entry.name == f"{CURRENT_NAME}{PARTIAL_SUFFIX}":  # never read: harmless
            report.notes.append(f"{message} (a compaction killed before its switch; removed "
                                "by the next writer's open)")
        else:
            report.notes.append(f"{message} (an interrupted write, never read; removed by "
                                "the next writer's open)")


def check_sequences(store: MapStore) -> CheckReport:
    """Only the sequence records, their indexes and counters: the part every other invariant
    (and a writer's recovery) builds on. O(sequences + edges) LMDB reads, no file touched."""
    report = CheckReport()
    with store.env.read() as txn:
        _check_sequences(MapRecords.read(store, txn), report)
    return report


def _check_sequences(records: MapRecords, report: CheckReport) -> None:
    """Sequences, names and dense vertex ranges: (seq, image) <-> vertex is one-to-one exactly
    when the ranges of the live sequences and the removed ranges together tile 0..total-1 with
    no gap or overlap."""
    counters, seqs = records.counters, records.seqs
    if counters["n_sequences"] != len(seqs):
        report.violation("lookup", f"meta says {counters['n_sequences']} sequences, "
                                   f"found {len(seqs)}")
    live_ids = {s.seq_id for s in seqs}
    for first, last, seq_id in records.removed:
        if last < first:
            report.violation("sequences", f"removed range {first}..{last} is empty")
        if seq_id in live_ids:
            report.violation("sequences", f"sequence {seq_id} is both live and removed")
        elif seq_id >= counters["next_seq_id"]:
            report.violation("lookup", f"removed sequence {seq_id} is beyond next_seq_id "
                                       f"{counters['next_seq_id']}")
    spans = sorted([(s.first_vertex, s.length, f"sequence {s.seq_id}") for s in seqs]
                   + [(a, b - a + 1, f"removed range {a}..{b}") for a, b, _ in records.removed])
    expected = 0
    for first, length, what in spans:
        if first != expected:
            report.violation("sequences", f"{what} starts at vertex {first}, expected "
                                          f"{expected}")
        expected = first + length
    for seq in sorted(seqs, key=lambda s: s.first_vertex):
        if seq.length < 1:
            report.violation("sequences", f"sequence {seq.seq_id} is empty")
        if records.vrange.get(seq.last_vertex) != seq.seq_id:
            report.violation("lookup", f"vertex range index has no entry for sequence "
                                       f"{seq.seq_id}")
        if records.names.get(seq.name) != seq.seq_id:
            report.violation("lookup", f"name {seq.name!r} does not map to sequence {seq.seq_id}")
        if seq.seq_id >= counters["next_seq_id"]:
            report.violation("lookup", f"sequence {seq.seq_id} is beyond next_seq_id "
                                       f"{counters['next_seq_id']}")
    if expected != records.total:
        report.violation("sequences", f"sequences cover {expected} vertices but meta says "
                                      f"{records.total}")
    removed = sum(b - a + 1 for a, b, _ in records.removed)
    if records.removed_vertices != removed:
        report.violation("removed", f"meta says {records.removed_vertices} removed vertices, "
                                    f"the removed ranges hold {removed}")
    for first, last in records.stray_positions:
        report.violation("removed", f"removed vertex range {first}..{last} still has positions")
    if len(records.vrange) != len(seqs):
        report.violation("lookup", f"vertex range index has {len(records.vrange)} entries for "
                                   f"{len(seqs)} sequences")
    if len(records.names) != len(seqs):
        report.violation("lookup", f"name index has {len(records.names)} entries for "
                                   f"{len(seqs)} sequences")


def check_shards(store: MapStore, total: int, report: CheckReport) -> None:
    """Each shard file holds at least its committed rows; extra bytes and files are notes.

    O(shards) ``stat`` calls.
    """
    shards = store.shards
    lengths = shards.lengths_for(total)
    last = max(lengths, default=-1)
    for shard, rows in lengths.items():
        path = shards.path(shard)
        size = path.stat().st_size if path.exists() else -1
        want = rows * shards.row_bytes
        if size < 0:
            report.violation("shard_files", f"shard file {path.name} is missing ({rows} "
                                            "committed rows)")
        elif size < want:
            report.violation("shard_files", f"shard file {path.name} is truncated: {size} "
                                            f"bytes, committed {want}")
        elif size > want:
            by = "the next writer's open or check --repair" if shard == last else "check --repair"
            report.notes.append(f"{path.name} has {size - want} uncommitted bytes (truncated by "
                                f"{by})")
    shard = last + 1
    while shards.path(shard).exists():
        report.notes.append(f"{shards.path(shard).name} holds no committed row (removed by the "
                            "next writer's open)")
        shard += 1


def _check_edges(records: MapRecords, report: CheckReport) -> None:
    """The reverse index mirrors the edges and the counter counts them (endpoints: in
    :func:`sequence_edges`)."""
    if records.counters["n_edges"] != len(records.edges):
        report.violation("edge_index", f"meta says {records.counters['n_edges']} edges, "
                                       f"found {len(records.edges)}")
    if sorted((d, s) for s, d in records.edges) != sorted(records.rev):
        report.violation("edge_index", "reverse edge index does not mirror the edges")


def edge_added_by(value: Raw) -> int:
    """The provenance field of an edge value: the sequence that added the edge, ``NO_QUERY``
    for none, ``MALFORMED`` if ``value`` is not an edge value. O(1)."""
    if len(value) != EDGE_VAL.size:
        return MALFORMED
    return read_u32(value[ADDED_BY_AT:ADDED_BY_AT + 4])


def _check_provenance(records: MapRecords, report: CheckReport) -> None:
    """Sequence ids follow vertex order, and each edge was added by a sequence below
    ``next_seq_id`` and no older than either of its ends (a drive's commit adds edges to itself
    and to earlier drives only). ``unmerge`` finds a drive's edges with one range scan that
    rests on both (:mod:`sprint_map.storage.provenance`).

    Notes
    -----
    O(n log n + E log n), vectorised over the edges.
    """
    ordered = sorted(records.seqs, key=lambda s: s.first_vertex)
    for prev, seq in zip(ordered, ordered[1:], strict=False):
        if seq.seq_id < prev.seq_id:
            report.violation("sequences", f"sequence {seq.seq_id} lies after sequence "
                                          f"{prev.seq_id} in vertex order (both follow commits)")
    if not records.edges or not ordered:
        return
    starts = np.array([s.first_vertex for s in ordered], dtype=np.int64)
    lasts = np.array([s.last_vertex for s in ordered], dtype=np.int64)
    ids = np.array([s.seq_id for s in ordered], dtype=np.int64)
    ends = np.minimum(np.array(records.edges, dtype=np.uint64), records.total).astype(np.int64)
    at = np.searchsorted(starts, ends, side="right") - 1
    inside = (at >= 0) & (ends <= lasts[np.maximum(at, 0)]) & (ends < records.total)
    newest = np.where(inside, ids[np.maximum(at, 0)], -1).max(axis=1)
    added = np.array(records.added_by, dtype=np.int64)
    given = (added != NO_QUERY) & (added != MALFORMED)
    limit = records.counters["next_seq_id"]
    for i in np.flatnonzero((added == MALFORMED) | (given & ((added >= limit) | (newest > added)))):
        (src, dst), by = records.edges[i], int(added[i])
        if by == MALFORMED:
            report.violation("edges", f"edge {src} -> {dst} has a malformed value")
        elif by >= limit:
            report.violation("edges", f"edge {src} -> {dst} was added by sequence {by}, beyond "
                                      f"next_seq_id {limit}")
        else:
            report.violation("edges", f"edge {src} -> {dst} joins sequence {int(newest[i])}, "
                                      f"newer than sequence {by} that added it")


def _check_components(records: MapRecords, edges: list[tuple[int, int, int, int]],
                      report: CheckReport) -> None:
    """Union-find is acyclic, matches the membership lists and totals, and partitions the
    sequences exactly as the edges do (networkx connected components)."""
    uf, by_id = records.uf, {s.seq_id: s for s in records.seqs}

    def bad(message: str) -> None:
        report.violation("components", message)

    roots: dict[int, int] = {}
    for seq_id in by_id:
        if seq_id not in uf:
            bad(f"sequence {seq_id} has no union-find record")
            continue
        node, steps = seq_id, 0
        while uf.get(node, (node,))[0] != node and steps <= len(uf):
            node, steps = uf[node][0], steps + 1
        if steps > len(uf) or node not in uf:
            bad(f"union-find chain of sequence {seq_id} is cyclic or dangling")
            continue
        roots[seq_id] = node
    if set(uf) != set(by_id):
        bad("union-find records do not match the sequences")
    groups: dict[int, set[int]] = {}
    for seq_id, root in roots.items():
        groups.setdefault(root, set()).add(seq_id)
    listed: dict[int, set[int]] = {}
    for root, member in records.members:
        listed.setdefault(root, set()).add(member)
    if listed != groups:
        bad("component membership lists disagree with union-find")
    for root, group in groups.items():
        if uf[root][1] != len(group):
            bad(f"component {root} size {uf[root][1]} != {len(group)} members")
        want_totals = (len(group), sum(by_id[s].length for s in group))
        if records.comp.get(root) != want_totals:
            bad(f"component {root} totals {records.comp.get(root)} != {want_totals}")
    if set(records.comp) != set(groups):
        bad("component totals exist for non-roots or are missing for roots")
    graph = nx.Graph()
    graph.add_nodes_from(by_id)
    graph.add_edges_from((a, b) for _, _, a, b in edges)
    from_edges = sorted(sorted(c) for c in nx.connected_components(graph))
    if from_edges != sorted(sorted(g) for g in groups.values()):
        bad("union-find components differ from the components recomputed from the edges")
    if records.counters["n_components"] != len(groups):
        bad(f"meta says {records.counters['n_components']} components, found {len(groups)}")
    report.checked["components"] = len(groups)


def check_thumbnails(store: MapStore, records: MapRecords, report: CheckReport,
                     decodes: ThumbnailTest | None = None) -> None:
    """Every thumbnail names a frame of a live sequence and is JPEG bytes; a sequence has
    one per frame or none. O(thumbnails) reads (see
    :func:`sprint_map.storage.thumbnails.scan_thumbnails`)."""
    with store.env.read() as txn:
        scan = scan_thumbnails(txn, store.env, {s.seq_id: s.length for s in records.seqs},
                               decodes)
    for problem in scan.problems:
        report.violation("thumbnails", problem)
    report.checked["thumbnails"] = sum(scan.counts.values())


def check_sightings(store: MapStore, records: MapRecords, report: CheckReport) -> None:
    """Every record of a place seen again names a frame of a live sequence and decodes.
    O(records) reads (see :func:`sprint_map.storage.sightings.scan_sightings`)."""
    with store.env.read() as txn:
        scan = scan_sightings(txn, store.env, {s.seq_id: s.length for s in records.seqs})
    for problem in scan.problems:
        report.violation("sightings", problem)
    report.checked["sightings"] = sum(scan.records.values())


def check_digests(store: MapStore, records: MapRecords, report: CheckReport) -> None:
    """Every sequence's shard rows hash to the digest committed with it (area
    ``shard_files``: rows changed in place, which no size reveals). Sequences written before
    digests were recorded are skipped (counted in ``checked["digests_missing"]``).

    Notes
    -----
    One streaming pass over the committed rows of the live sequences, ``CHECK_BLOCK`` rows
    at a time through the shards' memory maps: O(vertices * dim) reads, O(CHECK_BLOCK * dim)
    memory.
    """
    verified = missing = 0
    for seq in records.seqs:
        want = records.digests.get(seq.seq_id)
        if want is None:
            missing += 1
            continue
        digest = hashlib.blake2b(digest_size=DIGEST_BYTES)
        try:
            for start in range(seq.first_vertex, seq.last_vertex + 1, CHECK_BLOCK):
                stop = min(seq.last_vertex + 1, start + CHECK_BLOCK)
                rows = store.shards.rows(start, stop, records.total)
                digest.update(rows.astype("<f4", copy=False).data)
        except (MapCorruptError, StorageIOError) as exc:  # sizes are checked by check_shards
            report.notes.append(f"rows of sequence {seq.seq_id} not hashed: {exc}")
            continue
        if digest.digest() != want:
            report.violation("shard_files", f"descriptor rows of sequence {seq.seq_id} "
                                            f"({seq.name!r}) differ from the digest committed "
                                            "with them: shard bytes were changed")
        verified += 1
    report.checked["sequence_digests_verified"] = verified
    if missing:
        report.checked["digests_missing"] = missing
        report.notes.append(f"{missing} sequence(s) were written before content digests: their "
                            "rows are checked for size only")


def check_index(store: MapStore, total: int, report: CheckReport, seed: int = 0, *,
                live: bool = False) -> None:
    """No index file is ahead of the map; the newest other one is whole, covers exactly
    ``0..upto-1`` and every one of its vectors equals its shard row bit for bit.

    With ``live`` (a writer holds the lock), a file ahead of our snapshot or removed while we
    look is the writer's work in flight: a note, not a violation.

    Notes
    -----
    O(file size) to read the newest file, O(upto * dim) to compare it with the shards, in
    blocks of ``CHECK_BLOCK`` rows (measured: about 1 s per million 128-d vectors, see
    ``docs/benchmarks.md``, "check, forgetting, robustness"). ``seed`` is unused by the exact index (every vector is
    compared) and kept for the segmented index's sample of codes.
    """
    def bad(message: str) -> None:
        report.violation("index", message)

    projected = check_projection(store.data_path / INDEX_DIR, store.config.dim, report, live)
    if projected is None:
        return
    directory, projection = projected
    config = store.config if projection is None else replace(store.config,
                                                              dim=projection.dim_out)
    dim = config.dim
    if has_segments(directory):
        check_segments(directory, config, store.shards, total, bad, report.notes,
                       report.checked, seed, live, projection)
        return
    files = index_files(directory)
    for upto, path in files:
        if upto > total:
            message = f"index file {path.name} is {file_problem(path, upto, total, dim)}"
            if live:
                report.notes.append(f"{message}, in flight")
            else:
                bad(message)
    trusted = [(u, p) for u, p in files if u <= total]
    if not trusted:
        if total:
            report.notes.append("no persisted index; it is rebuilt from the shards on first use")
        return
    upto, path = trusted[-1]
    try:
        index = faiss.read_index(str(path))
    except RuntimeError as exc:
        if live and not path.exists():
            report.notes.append(f"index file {path.name} was replaced by the live writer")
        else:
            bad(f"index file {path.name} is unreadable: {exc}")
        return
    if index.ntotal != upto or index.d != dim:
        bad(f"index file {path.name} holds {index.ntotal} vectors of dim {index.d}, "
            f"stamped {upto} of dim {dim}")
        return
    problem = file_problem(path, upto, total, dim)
    if problem is not None and live and not path.exists():
        report.notes.append(f"index file {path.name} was replaced by the live writer")
    elif problem is not None:  # readable, yet not the file persist wrote (e.g. bytes appended)
        bad(f"index file {path.name} is {problem}")
        return
    ids = faiss.vector_to_array(index.id_map) if hasattr(index, "id_map") else np.arange(upto)
    if not np.array_equal(np.sort(ids), np.arange(upto)):
        bad(f"index file {path.name} does not cover vertices 0..{upto - 1}")
        return
    if upto < total:
        report.notes.append(f"index lags the map by {total - upto} vertices (caught up on load)")
    report.checked["index_vectors_compared"] = _compare_all(store, index, ids, upto, total,
                                                            report, bad, projection)


def check_projection(index_dir: Path, dim_in: int, report: CheckReport, live: bool
                     ) -> tuple[Path, Projection | None] | None:
    """The learned projection (area ``index``): its pointer parses, the file it names has
    its recorded size and checksum and the map's input dimension. Returns the directory of
    the index to check and the projection (None: the plain index in ``index/``), or None if
    the projection is bad (the index under it is then not checked). Directories it does not
    name are notes (removed by the next writer's open). O(projection bytes)."""
    try:
        learned = read_learned(index_dir)
    except ValueError as exc:
        report.violation("index", f"projection pointer {LEARNED} is unusable: {exc}")
        return None
    named = learned.directory_name if learned.generation else None
    for entry in projection_dirs(index_dir):
        if entry.name != named:
            report.notes.append(f"index directory {entry.name}/ is not the learned projection "
                                "(an interrupted learning; removed by the next writer's open)")
    if not learned.generation:
        return index_dir, None
    try:
        projection = learned.read_projection(index_dir)
    except FileNotFoundError as exc:
        if live:  # the writer replaced it since we read the pointer
            report.notes.append(f"learned projection replaced by the live writer ({exc})")
        else:
            report.violation("index", f"learned projection is missing: {exc}")
        return None
    except (ValueError, OSError) as exc:
        report.violation("index", f"learned projection is unusable: {exc}")
        return None
    if projection.dim_in != dim_in:
        report.violation("index", f"learned projection takes {projection.dim_in} dims, the "
                         f"map's descriptors have {dim_in}")
        return None
    report.checked["projection_verified"] = 1
    return index_dir / learned.directory_name, projection


def _compare_all(store: MapStore, index: Any, ids: np.ndarray, upto: int, total: int,
                 report: CheckReport, bad: Callable[[str], None],
                 projection: Projection | None = None) -> int:
    """Compare every vector of the flat ``index`` (ids ``ids``, a permutation of
    ``0..upto-1``) with its shard row, ``CHECK_BLOCK`` vertices at a time; report the first
    block that differs. Returns how many vectors were compared. O(upto * dim)."""
    inner = faiss.downcast_index(index.index) if hasattr(index, "id_map") else index
    if not hasattr(inner, "get_xb"):
        bad(f"index holds a {type(inner).__name__}, not a flat index")
        return 0
    dim = store.config.dim if projection is None else projection.dim_out
    vectors = faiss.rev_swig_ptr(inner.get_xb(), upto * dim).reshape(upto, dim)
    in_order = bool(np.array_equal(ids, np.arange(upto)))
    where = None if in_order else np.argsort(ids)  # where[v]: position of vertex v
    compared = 0
    for start in range(0, upto, CHECK_BLOCK):
        stop = min(upto, start + CHECK_BLOCK)
        try:
            rows = store.shards.rows(start, stop, total)
        except (MapCorruptError, StorageIOError) as exc:  # reported by check_shards
            report.notes.append(f"index vectors from vertex {start} on not compared: {exc}")
            break
        stored = vectors[start:stop] if where is None else vectors[where[start:stop]]
        if projection is not None:
            rows = projection.apply(rows)  # float64 then rounded: equal, but for a last bit
        if not (np.array_equal(stored, rows) if projection is None
                else np.allclose(stored, rows, rtol=0, atol=1e-6)):
            differ = start + int(np.flatnonzero((stored != rows).any(axis=1))[0])
            bad(f"index vector of vertex {differ} differs from its shard row")
            break
        compared = stop
    return compared


def partial_files(store: MapStore) -> list[Path]:
    """Leftover ``*.partial`` files of interrupted publications (map, generation, shards and
    index dirs)."""
    dirs = dict.fromkeys((store.path, store.data_path, store.data_path / SHARDS_DIR,
                          store.data_path / INDEX_DIR,
                          *projection_dirs(store.data_path / INDEX_DIR)))
    return [entry for directory in dirs
            if directory.is_dir() for entry in sorted(directory.iterdir())
            if entry.name.endswith(PARTIAL_SUFFIX)]
