"""Copying drives of another map into this one: rows, records, per-drive data and edges.

``sprint-map join TARGET SOURCE`` brings drives of SOURCE into TARGET with everything they carry.
This module is the storage half (no HMM): :func:`plan_join` decides what is copied and checks it
before anything is written, :func:`copy_drives` writes the rows and commits everything in ONE
LMDB transaction of the target (the group writer's, :mod:`sprint_map.storage.group_writer`), so
a join is wholly in the target or not at all. The localisation of the imported drives against
the target (their cross-map edges) is :mod:`sprint_map.merge.join`'s; they arrive here as edges.

**What a drive carries.** Its descriptor rows (verified against the content digest the source
committed with them, and the digest committed with the copy), its positions and fixes
(``vertex_data``), and its records in every *per-drive database*: each database of
:data:`~sprint_map.storage.lmdb_env.DB_NAMES` that is not one of :data:`STRUCTURE_DBS` is keyed
by the drive's ``>I`` seq_id first (``thumbnails``, ``sightings``, and any added later, such as
per-drive statistics), so it is copied generically: every record under the drive's prefix, the
prefix renumbered, the rest of the key and the value as they are. Its edges to the other drives
that the target holds after the join (imported with it, or already there) are copied with their
provenance (``added_by`` renumbered; an edge added by a drive the join does not carry is
credited to the newer of its two ends, the only drive whose commit could have written it) and
their times; an edge to a drive the target will not hold is left out (counted).

**Recognised twice.** A source drive whose rows the target already holds (same length and
content digest) is not copied again: it is ``present_as`` that sequence, and the edges between
it and the imported drives are carried to it. Joining the same source twice is therefore a
no-op.

**Read-only source.** Only read transactions and memory-mapped reads touch SOURCE; the caller
holds a shared lock on it so that no writer changes it meanwhile.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import AbstractContextManager, contextmanager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import lmdb
import numpy as np

from sprint_map.errors import (
    DuplicateNameError,
    InputError,
    MapCorruptError,
    MapLockedError,
    StorageIOError,
    UnknownSequenceError,
)
from sprint_map.storage.generation import current_data
from sprint_map.storage.keys import (
    DIGEST_BYTES,
    EDGE_KEY,
    EDGE_VAL,
    NO_QUERY,
    VERTEX_VAL,
    VERTEX_VAL_SIGMA,
    u32,
    u64,
)
from sprint_map.storage.lmdb_env import DB_NAMES, lock_out_writers
from sprint_map.storage.records import AddResult, EdgeSpec, SequenceRecord
from sprint_map.storage.store import MapStore
from sprint_map.testing.crash import crash_point
from sprint_map.util.arrays import Descriptors
from sprint_map.util.validation import decode_text, validate_name

__all__ = ["COPY_BATCH", "STRUCTURE_DBS", "CopiedDrive", "ImportedDrive", "JoinPlan",
           "copy_drives", "drive_rows", "open_source_map", "per_drive_dbs", "plan_join"]

#: The databases that make the map's structure (written record by record by the commit); every
#: other one is per drive, keyed by ``>I`` seq_id first, and copied generically.
STRUCTURE_DBS = frozenset({
    "meta", "sequences", "seq_names", "vrange", "vertex_data", "edges", "edges_rev", "uf",
    "members", "comp", "shards", "removed", "digests"})

#: Rows read from the source and written to the target at a time (memory: this times 4 * dim).
COPY_BATCH = 16_384


@contextmanager
def open_source_map(path: str | os.PathLike[str], target: MapStore,
                    check_config: Callable[[dict[str, Any]], object] | None = None
                    ) -> Iterator[MapStore]:
    """Open the map at ``path`` read-only as the source of a join into ``target``, and keep
    every writer out of it until the block ends (a shared lock on its ``LOCK``; nothing of it is
    written, so a read-only file system serves). ``check_config`` is called with its config
    record (the facade's checks of what storage does not read).

    Raises
    ------
    InputError
        ``path`` is ``target`` itself.
    MapLockedError
        A writer is at work on the source (its commits would race the copy).
    NotAMapError, MapCorruptError, SchemaVersionError
        As for any read-only open.
    """
    root = Path(decode_text(os.fspath(path), "source map path"))
    try:
        same = root.exists() and os.path.samefile(root, target.path)
    except OSError:
        same = False
    if same or (root.exists() and current_data(root) == target.data_path):
        raise InputError(f"{root}: the source of a join is the target map itself")
    try:
        fd = lock_out_writers(root) if root.is_dir() else None
    except MapLockedError:
        raise MapLockedError(f"{root}: the source map is being written by another process; "
                             "join it once that writer is done (nothing was changed)") from None
    try:
        store = MapStore.open(root, readonly=True)
        try:
            if check_config is not None:
                check_config(store.config_record)
            yield store
        finally:
            store.close()
    finally:
        if fd is not None:
            os.close(fd)


def per_drive_dbs(source: MapStore) -> list[str]:
    """The per-drive databases ``source`` has (see the module docstring), in ``DB_NAMES`` order."""
    return [name for name in DB_NAMES if name not in STRUCTURE_DBS and source.env.has_db(name)]


@dataclass(frozen=True)
class ImportedDrive:
    """One source drive of a join: its source record and digest, the name it takes in the
    target, and the target's sequence that already holds its rows (None: it is copied)."""

    source: SequenceRecord
    name: str
    digest: bytes
    present_as: SequenceRecord | None = None


@dataclass(frozen=True)
class JoinPlan:
    """What a join copies, decided before anything is written (:func:`plan_join`)."""

    drives: list[ImportedDrive]
    #: source edges carried (between two drives the target holds after the join, one of
    #: them copied by it)
    edges: int = 0
    #: source edges left out: an end in a drive the target will not hold
    edges_dropped: int = 0
    #: source sequence pairs joined by the carried edges (for connectivity)
    links: frozenset[tuple[int, int]] = field(default_factory=frozenset)
    #: the source's per-drive databases (copied)
    databases: tuple[str, ...] = ()

    @property
    def imports(self) -> list[ImportedDrive]:
        """The drives copied (those the target does not hold yet), in source order."""
        return [d for d in self.drives if d.present_as is None]


@dataclass(frozen=True)
class CopiedDrive:
    """One drive the join committed: its source record, and what it is in the target."""

    source: SequenceRecord
    added: AddResult


def drive_rows(store: MapStore, record: SequenceRecord, total: int,
               batch: int = COPY_BATCH) -> Iterator[Descriptors]:
    """The rows of sequence ``record`` of ``store`` (holding ``total`` vertices), ``batch`` at a
    time, read with ``pread`` (no memory map: the pages read do not stay in this process's
    memory, so a copy of a large map holds one batch at a time).

    Raises
    ------
    MapCorruptError
        A shard shorter than its committed rows (never read past its end).
    StorageIOError
        A shard that cannot be read.
    """
    shards = store.shards
    fds: dict[int, int] = {}
    try:
        for first in range(record.first_vertex, record.last_vertex + 1, batch):
            stop = min(first + batch, record.last_vertex + 1)
            parts = []
            row = first
            while row < stop:
                shard, offset = divmod(row, shards.shard_rows)
                take = min(stop - row, shards.shard_rows - offset)
                if shard not in fds:
                    committed = min(shards.shard_rows, total - shard * shards.shard_rows)
                    problem = shards.size_problem(shard, committed)
                    if problem is not None:
                        raise MapCorruptError(f"{problem}: committed descriptors are lost")
                    try:
                        fds[shard] = os.open(shards.path(shard), os.O_RDONLY | os.O_CLOEXEC)
                    except OSError as exc:
                        raise StorageIOError(f"cannot read {shards.path(shard)}: {exc}") from exc
                want = take * shards.row_bytes
                try:
                    data = os.pread(fds[shard], want, offset * shards.row_bytes)
                except OSError as exc:
                    raise StorageIOError(f"cannot read {shards.path(shard)}: {exc}") from exc
                if len(data) != want:
                    raise MapCorruptError(f"{shards.path(shard)} ends inside committed rows")
                parts.append(np.frombuffer(data, dtype="<f4").reshape(take, shards.dim))
                row += take
            yield parts[0] if len(parts) == 1 else np.concatenate(parts)
    finally:
        for fd in fds.values():
            os.close(fd)


def _rows_digest(store: MapStore, record: SequenceRecord, total: int) -> bytes:
    digest = hashlib.blake2b(digest_size=DIGEST_BYTES)
    for rows in drive_rows(store, record, total):
        digest.update(rows.astype("<f4", copy=False).data)
    return digest.digest()


def plan_join(target: MapStore, source: MapStore, drives: Sequence[str] | None = None,
              prefix: str = "") -> JoinPlan:
    """What joining ``drives`` of ``source`` (names; None: every drive) into ``target`` copies.

    Each drive takes the name ``prefix + its name``. A drive whose rows the target already
    holds (same length and content digest) is ``present_as`` that sequence and not copied.

    Raises
    ------
    UnknownSequenceError
        A name in ``drives`` that ``source`` does not have (every such name is listed).
    DuplicateNameError
        Names the target already gives to other drives (every such name is listed; ``prefix``
        resolves them), or two drives of the join that would share one.
    InputError
        A ``prefix`` that makes a name the name rules refuse.

    Notes
    -----
    O(n) sequence records and digests of both maps, one pass over the source's edges from the
    carried drives (O(E log n)), and a hash of the rows of a source drive committed without a
    digest (an older writer). Memory: O(n + links).
    """
    seqs = source.sequences()
    if drives is not None:
        wanted = list(dict.fromkeys(drives))
        by_name = {s.name: s for s in seqs}
        missing = [n for n in wanted if n not in by_name]
        if missing:
            raise UnknownSequenceError(
                f"the source map has no drive named {', '.join(map(repr, missing))} "
                f"(its drives: {', '.join(s.name for s in seqs[:20])}"
                f"{', ...' if len(seqs) > 20 else ''})")
        chosen = set(wanted)
        seqs = [s for s in seqs if s.name in chosen]
    with source.env.read() as stxn:
        total = source.counter("next_vertex_id", stxn)
        stored = {s.seq_id: source.sequence_digest(s.seq_id, stxn) for s in seqs}
    digests: dict[int, bytes] = {}
    for s in seqs:
        digest = stored[s.seq_id]
        digests[s.seq_id] = digest if digest is not None else _rows_digest(source, s, total)
    held: dict[tuple[int, bytes], SequenceRecord] = {}
    with target.env.read() as ttxn:
        for rec in target.sequences():
            digest = target.sequence_digest(rec.seq_id, ttxn)
            if digest is not None:
                held.setdefault((rec.length, digest), rec)
        names = target.env.db("seq_names")
        out, taken, twice = [], [], []
        seen: set[str] = set()
        for s in seqs:
            present = held.get((s.length, digests[s.seq_id]))
            name = prefix + s.name
            if present is None:
                validate_name(name)
                if txn_has(ttxn, names, name):
                    taken.append(name)
                if name in seen:
                    twice.append(name)
                seen.add(name)
            out.append(ImportedDrive(s, name, digests[s.seq_id], present))
    if taken:
        raise DuplicateNameError(
            f"the target map already has drive(s) named {', '.join(map(repr, taken))}: join "
            "with --prefix to rename the imported ones, or choose drives with --drives")
    if twice:
        raise DuplicateNameError(f"two imported drives would both be named {twice[0]!r}")
    plan = JoinPlan(out, databases=tuple(per_drive_dbs(source)))
    carried, dropped, links = 0, 0, set()
    for _src, _dst, _value, pair in _carried_edges(source, plan, _ids(plan)):
        if pair is None:
            dropped += 1
        else:
            carried += 1
            links.add(pair)
    return JoinPlan(out, carried, dropped, frozenset(links), plan.databases)


def txn_has(txn: lmdb.Transaction, db: lmdb._Database, name: str) -> bool:
    return txn.get(name.encode(), db=db) is not None


def _ids(plan: JoinPlan, copied: Sequence[SequenceRecord] = ()) -> dict[int, int]:
    """Source seq_id -> target seq_id of every drive the target holds after the join: the
    present ones now, the copied ones once ``copied`` (their target records, in plan order)
    are known (before that, the copied ones map to -1)."""
    ids = {d.source.seq_id: d.present_as.seq_id if d.present_as is not None else -1
           for d in plan.drives}
    for d, rec in zip(plan.imports, copied, strict=False):
        ids[d.source.seq_id] = rec.seq_id
    return ids


def _carried_edges(source: MapStore, plan: JoinPlan, ids: dict[int, int]
                   ) -> Iterator[tuple[int, int, bytes, tuple[int, int] | None]]:
    """The source edges from the plan's drives: ``(src, dst, value, (src_seq, dst_seq))`` for an
    edge to carry (source ids), ``pair`` None for one to leave out. An edge between two present
    drives is neither (the target has it, or chose not to). O(E log n), one read snapshot."""
    seqs = sorted(source.sequences(), key=lambda s: s.first_vertex)
    starts = np.array([s.first_vertex for s in seqs], dtype=np.int64)
    lasts = np.array([s.last_vertex for s in seqs], dtype=np.int64)
    owner = [s.seq_id for s in seqs]
    present = {d.source.seq_id for d in plan.drives if d.present_as is not None}

    def seq_of(vertex: int) -> int | None:
        at = int(np.searchsorted(starts, vertex, side="right")) - 1
        return owner[at] if at >= 0 and vertex <= lasts[at] else None

    with source.env.read() as txn:
        cursor = txn.cursor(db=source.env.db("edges"))
        for d in plan.drives:
            rec = d.source
            if not cursor.set_range(EDGE_KEY.pack(rec.first_vertex, 0)):
                continue
            for key, value in cursor:
                src, dst = EDGE_KEY.unpack(key)
                if src > rec.last_vertex:
                    break
                other = seq_of(dst)
                if other is None:
                    raise MapCorruptError(f"source edge {src} -> {dst} ends outside every "
                                          "live sequence")
                if other not in ids:
                    yield src, dst, bytes(value), None
                elif not (rec.seq_id in present and other in present):
                    yield src, dst, bytes(value), (rec.seq_id, other)


def copy_drives(target: MapStore, source: MapStore, plan: JoinPlan,
                cross_edges: dict[int, list[EdgeSpec]],
                progress: Callable[[int], None] | None = None, *,
                exclusive: Callable[[], AbstractContextManager[Any]] | None = None,
                on_commit: Callable[[set[int]], None] | None = None) -> list[CopiedDrive]:
    """Copy the plan's drives (:attr:`JoinPlan.imports`) into ``target`` in one commit.

    ``cross_edges``: per source seq_id, the edges the join's merge adds from that drive (``None``
    ends: the drive itself), written with it (provenance: the drive). ``progress``: rows copied
    since its last call. ``exclusive``: held around the transaction, the index's catch-up and
    ``on_commit`` only (a service's gate; the rows are fsynced before); ``on_commit``: given the
    components the join changed. Rows stream from the source's shards (:data:`COPY_BATCH` at a
    time), hashed against the source's digest; one group transaction records every drive, its
    per-drive databases and carried edges, and the source's geographic frame if the target has
    none (crash points ``group.rows_written``, ``join.records_copied``, ``group.before_commit``,
    ``group.committed``).

    Raises
    ------
    MapCorruptError
        A source drive's rows that differ from its digest (nothing is committed).
    StorageIOError
        The target cannot be written (a full disk: nothing is committed, its rows truncated).

    Notes
    -----
    O(N * dim) row I/O, O(N) position and per-drive records and O(E log n) edges in one
    transaction; memory O(COPY_BATCH * dim + one drive's positions).
    """
    with source.env.read() as stxn:
        total = source.counter("next_vertex_id", stxn)
        geo = stxn.get(b"geo_frame", db=source.env.db("meta"))
    with target.begin_group() as group:
        for d in plan.imports:
            rec = d.source

            def rows(rec: SequenceRecord = rec) -> Iterator[Descriptors]:
                for batch in drive_rows(source, rec, total):
                    yield batch
                    if progress is not None:
                        progress(len(batch))

            # positions are copied as records in the transaction (``_copy_positions``)
            group.add(rows(), d.name, rec.source, None, cross_edges.get(rec.seq_id, ()))
            if group.digests[-1] != d.digest:
                raise MapCorruptError(f"the source's drive {rec.name!r} (sequence {rec.seq_id}) "
                                      "has rows that differ from its content digest: run "
                                      "`sprint-map check` on the source")
        staged = group.staged
        ids = _ids(plan, staged)

        def extra(txn: lmdb.Transaction) -> None:
            with source.env.read() as src_txn:
                _copy_positions(target, txn, source, src_txn, plan, staged)
                for name in plan.databases:
                    _copy_db(target, txn, source, src_txn, name, plan, ids)
            _put_edges(target, txn, source, plan, ids)
            if geo is not None and txn.get(b"geo_frame", db=target.env.db("meta")) is None:
                txn.put(b"geo_frame", bytes(geo), db=target.env.db("meta"))
            crash_point("join.records_copied")

        before: set[int] = set()
        if on_commit is not None:  # only this writer changes the union-find: roots hold
            reached = {seq for edges in cross_edges.values() for e in edges
                       for seq, _ in (e.src, e.dst) if seq is not None}
            reached |= {d.present_as.seq_id for d in plan.drives if d.present_as is not None}
            before = {target.component_of(seq) for seq in reached}
        if exclusive is not None:
            target.shards.sync()  # the rows' fsync, the slow part, before the gate
        with exclusive() if exclusive is not None else nullcontext():
            results = group.commit(extra)
            if on_commit is not None:
                on_commit(before | {target.component_of(r.sequence.seq_id) for r in results})
    return [CopiedDrive(d.source, r) for d, r in zip(plan.imports, results, strict=True)]


def _copy_positions(target: MapStore, txn: lmdb.Transaction, source: MapStore,
                    src_txn: lmdb.Transaction, plan: JoinPlan,
                    copied: Sequence[SequenceRecord]) -> None:
    """Copy the imported drives' ``vertex_data`` records (positions and fixes), their keys
    shifted to the copies' vertex ids and their values as they are (checked: one of the two
    record widths). O(N) records, keys renumbered with numpy a drive at a time."""
    db = target.env.db("vertex_data")
    cursor = src_txn.cursor(db=source.env.db("vertex_data"))
    for d, rec in zip(plan.imports, copied, strict=True):
        first, last = d.source.first_vertex, d.source.last_vertex
        if not cursor.set_range(u64(first)):
            continue
        keys, values = [], []
        for key, value in cursor:
            if len(key) != 8 or bytes(key) > u64(last):
                break
            if len(value) not in (VERTEX_VAL.size, VERTEX_VAL_SIGMA.size):
                raise MapCorruptError(f"the source's position record of vertex "
                                      f"{int.from_bytes(key, 'big')} is {len(value)} bytes")
            keys.append(bytes(key))
            values.append(bytes(value))
        if not keys:
            continue
        ids = np.frombuffer(b"".join(keys), dtype=">u8").astype(np.int64)
        new = (ids - first + rec.first_vertex).astype(">u8").tobytes()
        consumed, added = txn.cursor(db=db).putmulti(
            ((new[8 * i: 8 * i + 8], v) for i, v in enumerate(values)), append=True)
        if added != consumed:
            raise MapCorruptError("the target's positions hold records past its last vertex: "
                                  "run `sprint-map check` on the target")


def _copy_db(target: MapStore, txn: lmdb.Transaction, source: MapStore,
             src_txn: lmdb.Transaction, name: str, plan: JoinPlan, ids: dict[int, int]) -> None:
    """Copy every record of the imported drives in per-drive database ``name``, renumbered."""
    db = target.env.db(name)
    cursor = src_txn.cursor(db=source.env.db(name))
    for d in plan.imports:
        prefix = u32(d.source.seq_id)
        new = u32(ids[d.source.seq_id])
        if not cursor.set_range(prefix):
            continue

        def records(cursor: lmdb.Cursor = cursor, prefix: bytes = prefix, new: bytes = new
                    ) -> Iterator[tuple[bytes, bytes]]:
            for key, value in cursor:
                if bytes(key[:4]) != prefix:
                    break
                yield new + bytes(key[4:]), bytes(value)

        # the new ids are past every id of the target: its keys sort last (appended); LMDB
        # skips, without an error, a key that does not sort after the database's last one
        consumed, added = txn.cursor(db=db).putmulti(records(), append=True)
        if added != consumed:
            raise MapCorruptError(f"the target's {name!r} database holds records of sequence "
                                  f"ids at or past {ids[d.source.seq_id]}, beyond its last "
                                  "sequence: run `sprint-map check` on the target")


def _put_edges(target: MapStore, txn: lmdb.Transaction, source: MapStore, plan: JoinPlan,
               ids: dict[int, int]) -> None:
    """Write the carried source edges with their endpoints and provenance renumbered, and the
    unions they make; keep the edge and component counters."""
    firsts = {d.source.seq_id: (d.source.first_vertex, d.present_as) for d in plan.drives}
    new_first: dict[int, int] = {}
    for sid, tid in ids.items():
        new_first[sid] = target.sequence(tid, txn).first_vertex
    edges_db, rev_db, meta = target.env.db("edges"), target.env.db("edges_rev"), \
        target.env.db("meta")
    added = 0
    joins: set[tuple[int, int]] = set()
    for src, dst, value, pair in _carried_edges(source, plan, ids):
        if pair is None:
            continue
        a, b = pair
        new_src = new_first[a] + src - firsts[a][0]
        new_dst = new_first[b] + dst - firsts[b][0]
        weight, query, frame, when = EDGE_VAL.unpack(value)
        newest = max(ids[a], ids[b])
        by = ids.get(query, -1) if query != NO_QUERY else NO_QUERY
        if by != NO_QUERY and by < newest:
            by = newest  # credited to a drive its commit could not have written it
        key = EDGE_KEY.pack(new_src, new_dst)
        if txn.get(key, db=edges_db) is None:
            added += 1
        txn.put(key, EDGE_VAL.pack(weight, by, frame, when), db=edges_db)
        txn.put(EDGE_KEY.pack(new_dst, new_src), b"", db=rev_db)
        joins.add((min(ids[a], ids[b]), max(ids[a], ids[b])))
    merged = 0
    for x, y in sorted(joins):
        if target.uf.find(txn, x) != target.uf.find(txn, y):
            target.uf.union(txn, x, y)
            merged += 1
    txn.put(b"n_edges", u64(target.counter("n_edges", txn) + added), db=meta)
    txn.put(b"n_components", u64(target.counter("n_components", txn) - merged), db=meta)
