"""Streaming one new sequence into a map: rows as they come, one atomic commit at the end.

A drive can be longer than memory allows (a 100k-frame video is 700 MB of HoG descriptors), so
its rows go to the shards batch by batch, invisible to readers (LMDB still records the old shard
lengths), while the caller localises each batch. :meth:`SequenceWriter.commit` then records the
sequence, its positions and edges in one LMDB transaction: the commit point. Leaving the ``with``
block without committing, or any error, truncates the shards back: nothing is half-visible. (If
the truncation fails too, the error that caused it is the one raised; the rows stay invisible
and the next writer's open truncates them.)

**Digests and idempotent retries.** The commit records a content digest of the rows (BLAKE2b,
16 bytes, over the little-endian float32 rows in order: ``digests`` database). A sequence whose
name is already committed *with a digest* is a possible retry: its rows are hashed but not
written, and at the commit the digest decides: the same rows (same length and digest) commit
nothing and report the existing sequence (``AddResult.already_committed``); other rows are a
:class:`DuplicateNameError`. So a retry after a failure past the commit point (which is only
ever a warning) never adds the drive twice. A name committed without a digest (by an older
writer) is refused at once, as before.
"""

from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Container, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, Self

import lmdb
import numpy as np

from sprint_map.errors import (
    DuplicateNameError,
    EmptySequenceError,
    InputError,
    MapCorruptError,
    SprintMapError,
    StorageIOError,
    UnknownSequenceError,
)
from sprint_map.storage.components import ComponentStore
from sprint_map.storage.drive_stats import encode_drive_stats, put_drive_stats
from sprint_map.storage.keys import (
    DIGEST_BYTES,
    EDGE_KEY,
    VERTEX_VAL,
    VERTEX_VAL_SIGMA,
    read_u32,
    u32,
    u64,
)
from sprint_map.storage.lmdb_env import LmdbEnv
from sprint_map.storage.records import AddResult, EdgeRecord, EdgeSpec, SequenceRecord
from sprint_map.storage.removal import RemovedRanges
from sprint_map.storage.shards import ShardSet
from sprint_map.storage.sightings import record_sightings
from sprint_map.storage.store_config import StoreConfig
from sprint_map.storage.thumbnails import put_thumbnails, validate_thumbnails
from sprint_map.testing.crash import crash_point
from sprint_map.util.validation import (
    validate_descriptors,
    validate_name,
    validate_positions,
)

__all__ = ["ResolvedEdge", "SequenceWriter", "StagedSequence", "UncommittedRows", "WritableMap",
           "default_name", "record_live_sightings", "resolve_edge", "write_sequence",
           "write_staged"]

#: An edge with global endpoints: (src vertex, dst vertex, src seq, dst seq, spec).
ResolvedEdge = tuple[int, int, int, int, EdgeSpec]


class WritableMap(Protocol):
    """What writing a sequence uses of a map open for writing (``MapStore`` is one).

    The writer reads the counters, sequences and digests, appends rows to the shards, writes
    one LMDB transaction (records, lookups, edges, union-find, counters) and then lets the map
    bring its index up to date.
    """

    @property
    def env(self) -> LmdbEnv: ...

    @property
    def uf(self) -> ComponentStore: ...

    @property
    def shards(self) -> ShardSet: ...

    @property
    def config(self) -> StoreConfig: ...

    @property
    def warnings(self) -> list[str]: ...

    @property
    def writing(self) -> object | None: ...

    def require_writer(self) -> None: ...

    def start_writing(self, writer: object) -> None: ...

    def end_writing(self, writer: object) -> None: ...

    def counter(self, name: str, txn: lmdb.Transaction | None = None) -> int: ...

    def sequence(self, seq_id: int, txn: lmdb.Transaction | None = None) -> SequenceRecord: ...

    def locate(self, vertex_ids: Iterable[int], txn: lmdb.Transaction | None = None
               ) -> list[tuple[int, int]]: ...

    def edges_from(self, first: int, last: int, txn: lmdb.Transaction | None = None
                   ) -> list[EdgeRecord]: ...

    def removed_ranges(self, txn: lmdb.Transaction) -> RemovedRanges: ...

    def sequence_digest(self, seq_id: int, txn: lmdb.Transaction) -> bytes | None: ...

    def component_of(self, seq_id: int, txn: lmdb.Transaction | None = None) -> int: ...

    def put_lookups(self, txn: lmdb.Transaction, record: SequenceRecord) -> None: ...

    def after_commit(self, first: int, frames: int) -> None: ...

    def record_sightings(self, drive: str, sightings: Sequence[tuple[int, int, float]]
                         ) -> int: ...


def default_name(seq_id: int, taken: Callable[[str], bool]) -> str:
    """The default name of sequence ``seq_id``: ``seq-<id>``, unless that name is ``taken``.

    Ids are not names: a user may have named an earlier drive ``seq-<id>`` (or a drive not
    committed yet may hold it), so a taken name is skipped for ``seq-<id>-2``, ``seq-<id>-3``,
    ... The first name not taken is returned; the loop ends because finitely many are taken.
    """
    name = f"seq-{seq_id}"
    suffix = 1
    while taken(name):
        suffix += 1
        name = f"seq-{seq_id}-{suffix}"
    return name


@dataclass(frozen=True)
class StagedSequence:
    """A sequence whose rows are written (not yet fsynced) and whose records are validated:
    what its LMDB transaction writes (:func:`write_staged`). Made by
    :meth:`SequenceWriter.stage`."""

    record: SequenceRecord
    #: BLAKE2b of the rows (the ``digests`` database)
    digest: bytes
    #: committed rows per shard once it is in
    lengths: dict[int, int]
    positions: np.ndarray | None
    edges: list[ResolvedEdge]
    thumbnails: list[bytes] | None
    #: ``(seq_id, image_id, distance)`` of the stored vertices the drive saw again
    #: (:mod:`sprint_map.storage.sightings`)
    sightings: tuple[tuple[int, int, float], ...] = ()
    #: the drive's statistics record (:mod:`sprint_map.storage.drive_stats`), or None
    stats: bytes | None = None


class UncommittedRows(ABC):
    """What a writer of uncommitted rows (:class:`SequenceWriter`, and the group writer) shares:
    a context manager that aborts when left without a commit, an abort that runs once, and an
    abort during an error that never masks it. Subclasses set ``store`` and ``_done`` and
    define :meth:`drop_rows`."""

    store: WritableMap
    _done: bool

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if not self._done:
            if exc_type is None:
                self.abort()
            else:
                self._rollback_after_error()

    def abort(self) -> None:
        """Drop the uncommitted rows (truncate the shards to the committed end); nothing is
        committed. Once: later calls, and calls after a commit, do nothing.

        Raises
        ------
        StorageIOError
            If the shards cannot be truncated; the rows stay invisible (LMDB never counted
            them) and the next writer's open truncates them.
        """
        if self._done:
            return
        self._done = True
        self.drop_rows()

    @abstractmethod
    def drop_rows(self) -> None:
        """:meth:`abort`'s work, called once by it: release the writer's hold on the store and
        truncate the shards to the committed end."""

    def _rollback_after_error(self) -> None:
        """:meth:`abort` while an error propagates: a failed rollback must not mask the error."""
        try:
            self.abort()
        except (StorageIOError, MapCorruptError) as exc:
            self.store.warnings.append(f"uncommitted rows not yet removed ({exc})")


class SequenceWriter(UncommittedRows):
    """Writes one new sequence into ``store``; use as a context manager.

    Parameters
    ----------
    store : WritableMap
        A map open for writing (a ``MapStore``); one sequence may be in progress at a time.
    name : str, optional
        Unique sequence name; checked now, before any row is written. The default is
        ``seq-<id>``, or the first of ``seq-<id>-2``, ``seq-<id>-3``, ... that no sequence of
        the map has and ``reserved`` does not hold (:func:`default_name`): a default never
        collides.
    source : str
        Free text recording where the sequence came from.
    reserved : container of str
        Names a default must also avoid (e.g. the service's sessions not committed yet).
    follows : sequence of SequenceRecord, optional
        Set by a :class:`~sprint_map.storage.group_writer.GroupWriter` only: the records of the
        sequences of its group staged before this one (uncommitted). This sequence then takes
        the ids after them, its name must differ from theirs, its edges may reach them, and it
        is committed by the group (:meth:`stage`, then the group's one transaction), which
        holds the map's writing slot. None: a lone sequence, committed by :meth:`commit`.
    """

    def __init__(self, store: WritableMap, name: str | None = None, source: str = "",
                 reserved: Container[str] = (),
                 follows: Sequence[SequenceRecord] | None = None) -> None:
        store.require_writer()
        if follows is None and store.writing is not None:
            raise SprintMapError("another sequence is already being written to this map")
        pending = {r.name for r in follows or ()}
        with store.env.read() as txn:
            if follows:
                self.seq_id = follows[-1].seq_id + 1
                self.first = follows[-1].first_vertex + follows[-1].length
            else:
                self.seq_id = store.counter("next_seq_id", txn)
                self.first = store.counter("next_vertex_id", txn)
            names = store.env.db("seq_names")
            if name is None:
                self.name = default_name(
                    self.seq_id, lambda candidate: candidate in reserved or candidate in pending
                    or txn.get(candidate.encode(), db=names) is not None)
            else:
                self.name = name
            validate_name(self.name)
            if self.name in pending:
                raise DuplicateNameError(f"two sequences of one group are named {self.name!r}")
            #: (record, digest) of the committed sequence of this name: rows are only hashed
            self.retry_of: tuple[SequenceRecord, bytes] | None = None
            existing = txn.get(self.name.encode(), db=names)
            if existing is not None:
                record = store.sequence(read_u32(existing), txn)
                digest = store.sequence_digest(record.seq_id, txn)
                if digest is None:
                    raise DuplicateNameError(
                        f"a sequence named {self.name!r} already exists (choose another name)"
                    )
                self.retry_of = (record, digest)
        self.store = store
        import hashlib  # (here: commands that only read a map never load OpenSSL)

        self._hash = hashlib.blake2b(digest_size=DIGEST_BYTES)
        self.source = source
        self.frames = 0
        self._lengths: dict[int, int] = {}
        self._stats: bytes | None = None
        self._done = False
        #: (first vertex, length) of the group's sequences staged before this one
        self._pending = {r.seq_id: (r.first_vertex, r.length) for r in follows or ()}
        self._grouped = follows is not None
        if not self._grouped:
            store.start_writing(self)

    def prepare(self, positions: Any, edges: Sequence[EdgeSpec], frames: int
                ) -> tuple[np.ndarray | None, list[ResolvedEdge]]:
        """Validate positions and edges for a sequence of ``frames`` frames (writes nothing)."""
        pos = validate_positions(positions, frames)
        # one sequence read per distinct sequence; a group's staged ones are known already
        lengths: dict[int, tuple[int, int]] = dict(self._pending)
        with self.store.env.read() as txn:
            resolved = [
                resolve_edge(self.store, e, self.seq_id, self.first, frames, txn, lengths)
                for e in edges
            ]
        return pos, resolved

    def append(self, rows: Any) -> None:
        """Write a batch of descriptor rows (validated; not yet visible; fsynced, all batches
        at once, by :meth:`commit`)."""
        if self._done:
            raise SprintMapError("the sequence was already committed or aborted")
        arr = np.asarray(rows)
        if arr.ndim == 2 and arr.shape[0] == 0:
            return
        try:
            arr = validate_descriptors(arr, self.store.config.dim, first_frame=self.frames)
            self._hash.update(arr.astype("<f4", copy=False).data)
            if self.retry_of is None:  # a possible retry writes nothing until it is decided
                # fsynced once, at the commit: not once per batch
                self._lengths.update(self.store.shards.append(self.first + self.frames, arr,
                                                              sync=False))
        except BaseException:
            self._rollback_after_error()
            raise
        self.frames += len(arr)

    def sync(self) -> None:
        """Make the rows appended so far durable now (one fsync per shard file written, as
        :meth:`commit` would; it then finds nothing left to sync): to keep the fsync out of a
        lock held around the commit. An error aborts the sequence (its rows are dropped).
        """
        try:
            self.store.shards.sync()
        except BaseException:
            self._rollback_after_error()
            raise

    def set_stats(self, frames: int, mean: np.ndarray) -> None:
        """Record the drive's statistics with the sequence (``frames`` driven, their ``mean``
        descriptor as given: :mod:`sprint_map.storage.drive_stats`); checked now (InputError),
        written by the commit's transaction. O(dim)."""
        self._stats = encode_drive_stats(frames, mean, self.store.config.dim)

    def stage(self, positions: Any = None, edges: Sequence[EdgeSpec] = (),
              thumbnails: Sequence[bytes] | None = None,
              sightings: Sequence[tuple[int, int, float]] = ()) -> StagedSequence | AddResult:
        """Validate the sequence's records and make it ready for its transaction; no more rows.

        Returns what the transaction writes (:func:`write_staged`, after the rows are fsynced:
        :meth:`commit` does both, a group does them once for all its sequences), or, for a
        retry of a sequence committed under this name with these very rows, its
        ``AddResult`` (``already_committed``: nothing to write). Once staged, the rows are the
        committer's to keep or truncate; this writer no longer drops them on exit.

        Raises
        ------
        EmptySequenceError
            If no row was appended. Any error aborts the sequence (its rows are dropped).
        InputError
            Bad positions or edges, or thumbnails not one per frame, or not JPEG bytes.
        DuplicateNameError
            A retry whose rows are not the committed sequence's.
        """
        try:
            if self._done:
                raise SprintMapError("the sequence was already committed or aborted")
            if self.frames == 0:
                raise EmptySequenceError("the sequence has no frames")
            digest = self._hash.digest()
            if self.retry_of is not None:
                return self._finish_retry(digest)
            pos, resolved = self.prepare(positions, edges, self.frames)
            thumbs = (None if thumbnails is None
                      else validate_thumbnails(thumbnails, self.frames))
            record = SequenceRecord(self.seq_id, self.name, self.frames, self.first, time.time(),
                                    self.source)
        except BaseException:
            self._rollback_after_error()
            raise
        self._done = True
        return StagedSequence(record, digest, dict(self._lengths), pos, resolved, thumbs,
                              tuple(sightings), self._stats)

    def commit(self, positions: Any = None, edges: Sequence[EdgeSpec] = (),
               thumbnails: Sequence[bytes] | None = None,
               sightings: Sequence[tuple[int, int, float]] = ()) -> AddResult:
        """Record the sequence with its positions, edges and thumbnails in one LMDB transaction.

        ``thumbnails``, if given, are one JPEG per frame (see
        :mod:`sprint_map.storage.thumbnails`); they are read here, at the commit, so a list a
        frame source fills while its batches stream is complete by then. ``sightings``:
        ``(seq_id, image_id, distance)`` of stored vertices the drive saw again, counted in the
        same transaction (:mod:`sprint_map.storage.sightings`).

        Raises
        ------
        EmptySequenceError
            If no row was appended. Any error aborts the sequence (nothing is committed).
        InputError
            Thumbnails not one per frame, or not JPEG bytes.
        SprintMapError
            A sequence of a group (its group commits it).
        """
        if self._grouped:
            raise SprintMapError("a sequence of a group is committed by its group")
        staged = self.stage(positions, edges, thumbnails, sightings)
        if isinstance(staged, AddResult):
            return staged
        record = staged.record
        try:
            self.store.shards.sync()  # the rows are durable before the commit that counts them
            crash_point("add.shards_written")
            component, added = self.store.env.write(
                lambda txn: write_staged(self.store, txn, staged))
        except BaseException:
            self._done = False  # staged, not committed: its rows are still this writer's
            self._rollback_after_error()
            raise
        self.store.end_writing(self)
        crash_point("add.committed")
        try:
            self.store.after_commit(self.first, self.frames)
        except Exception as exc:
            # The sequence is committed and durable; the index is a cache of it. Failing the
            # call would invite a retry (which would find the sequence committed, see the
            # module docstring): past the commit point every failure is a warning.
            self.store.warnings.append(f"sequence {record.name!r} committed, but the index "
                                       f"cache was not updated ({exc}); rebuilt when needed")
        return AddResult(record, component, added)

    def _finish_retry(self, digest: bytes) -> AddResult:
        """Commit nothing for rows that equal the committed sequence of this name; refuse
        others (DuplicateNameError). No shard row was written (see :meth:`append`)."""
        assert self.retry_of is not None
        record, committed = self.retry_of
        if self.frames != record.length or digest != committed:
            raise DuplicateNameError(
                f"a sequence named {self.name!r} already exists with other descriptors "
                f"({record.length} frames; choose another name)")
        self._done = True
        if not self._grouped:
            self.store.end_writing(self)
        self.store.warnings.append(
            f"sequence {record.name!r} was already committed with these very descriptors (as "
            f"sequence {record.seq_id}): nothing added")
        return AddResult(record, self.store.component_of(record.seq_id), 0,
                         already_committed=True)

    def drop_rows(self) -> None:
        """Drop every row appended so far (see :meth:`abort`)."""
        if not self._grouped:
            self.store.end_writing(self)
        if self.retry_of is None:  # a possible retry wrote no row
            self.store.shards.recover(self.first)


def resolve_edge(store: WritableMap, edge: EdgeSpec, new_seq: int, first: int, n: int,
                 txn: lmdb.Transaction,
                 seen: dict[int, tuple[int, int]] | None = None) -> ResolvedEdge:
    """Global endpoints of ``edge`` for a new sequence ``new_seq`` of ``n`` frames from vertex
    ``first``; ``seen`` caches ``seq_id -> (first vertex, length)`` across the edges of one
    commit (a drive's edges hit few sequences, many times). O(log n_sequences) per sequence.

    Raises
    ------
    InputError
        An endpoint outside the new sequence, an edge within one sequence, a weight outside
        [0, 1].
    UnknownSequenceError
        An endpoint in a sequence the map does not have, or past its last image.
    """
    ends = []
    for seq, image in (edge.src, edge.dst):
        if seq is None or seq == new_seq:
            if not 0 <= image < n:
                raise InputError(f"edge endpoint image {image} outside the new sequence")
            ends.append((new_seq, first + image))
            continue
        span = seen.get(seq) if seen is not None else None
        if span is None:
            record = store.sequence(seq, txn)
            span = (record.first_vertex, record.length)
            if seen is not None:
                seen[seq] = span
        if not 0 <= image < span[1]:
            raise UnknownSequenceError(
                f"sequence {seq} has no image {image} (it has {span[1]})")
        ends.append((seq, span[0] + image))
    (src_seq, src), (dst_seq, dst) = ends
    if src_seq == dst_seq:
        raise InputError(f"edge {edge.src} -> {edge.dst} does not join two sequences")
    if not (0 <= edge.weight <= 1 and math.isfinite(edge.weight)):
        raise InputError(f"edge weight must be in [0, 1], got {edge.weight}")
    return src, dst, src_seq, dst_seq, edge

def write_staged(store: WritableMap, txn: lmdb.Transaction, staged: StagedSequence
                 ) -> tuple[int, int]:
    """Record a staged sequence in ``txn``: its digest, thumbnails and everything
    :func:`write_sequence` writes. Returns ``(component, edges added)``. Safe to run again in a
    new transaction (``LmdbEnv.write`` retries a full map)."""
    txn.put(u32(staged.record.seq_id), staged.digest, db=store.env.db("digests"))
    if staged.stats is not None:
        put_drive_stats(txn, store.env, staged.record.seq_id, staged.stats)
    if staged.thumbnails is not None:
        put_thumbnails(txn, store.env, staged.record.seq_id, staged.thumbnails)
        crash_point("add.thumbnails_written")
    if staged.sightings:
        record_live_sightings(store, txn, staged.sightings, staged.record.name)
    return write_sequence(store, txn, staged.record, staged.lengths, staged.positions,
                          staged.edges)


def record_live_sightings(store: WritableMap, txn: lmdb.Transaction,
                          sightings: Sequence[tuple[int, int, float]], drive: str) -> int:
    """Count ``sightings`` (``(seq_id, image_id, distance)``) by ``drive`` in ``txn``, but
    those of vertices no longer in the map (a sequence removed since the drive was localised:
    they are statistics, dropped). Returns how many were counted. O(m log n)."""
    live: dict[int, int] = {}
    kept = []
    for seq_id, image_id, distance in sightings:
        if seq_id not in live:
            try:
                live[seq_id] = store.sequence(seq_id, txn).length
            except UnknownSequenceError:
                live[seq_id] = 0
        if 0 <= image_id < live[seq_id]:
            kept.append((seq_id, image_id, distance))
    return record_sightings(txn, store.env, kept, drive, time.time())


def write_sequence(store: WritableMap, txn: lmdb.Transaction, record: SequenceRecord,
                   lengths: dict[int, int], pos: np.ndarray | None, edges: list[ResolvedEdge]
                   ) -> tuple[int, int]:
    """Record a new sequence in ``txn``: its record and lookups, positions, committed shard
    lengths, union-find entry, ``edges`` (a repeated edge keeps its newest provenance) with
    the unions they make, and the counters. Returns ``(component, edges added)``.

    Notes
    -----
    O(N) LMDB puts for N positions + O(E log n) for E edges and their unions.
    """
    db = store.env.db
    meta = db("meta")
    txn.put(u32(record.seq_id), record.encode(), db=db("sequences"))
    store.put_lookups(txn, record)
    if pos is not None:
        vdb = db("vertex_data")
        txn.cursor(db=vdb).putmulti(  # frames without a fix get no record
            ((u64(record.first_vertex + i),
              VERTEX_VAL.pack(*row[:4]) if math.isnan(row[4]) else VERTEX_VAL_SIGMA.pack(*row))
             for i, row in enumerate(pos.tolist()) if not math.isnan(row[0])),
            append=True,
        )
    for shard, length in lengths.items():
        txn.put(u32(shard), u64(length), db=db("shards"))
    store.uf.add(txn, record.seq_id, record.length)
    n_components = store.counter("n_components", txn) + 1
    added = 0
    now = time.time()
    edges_db, rev_db = db("edges"), db("edges_rev")
    joined: set[tuple[int, int]] = set()  # sequence pairs already united in this commit
    for src, dst, src_seq, dst_seq, spec in edges:
        key = EDGE_KEY.pack(src, dst)
        value = EdgeRecord(src, dst, spec.weight, record.seq_id, spec.frame, now).encode_value()
        if txn.get(key, db=edges_db) is None:
            added += 1
        txn.put(key, value, db=edges_db)  # a repeated edge keeps its newest provenance
        txn.put(EDGE_KEY.pack(dst, src), b"", db=rev_db)
        pair = (src_seq, dst_seq) if src_seq < dst_seq else (dst_seq, src_seq)
        if pair in joined:
            continue
        joined.add(pair)
        if store.uf.find(txn, src_seq) != store.uf.find(txn, dst_seq):
            store.uf.union(txn, src_seq, dst_seq)
            n_components -= 1
    txn.put(b"next_seq_id", u64(record.seq_id + 1), db=meta)
    txn.put(b"next_vertex_id", u64(record.first_vertex + record.length), db=meta)
    txn.put(b"n_sequences", u64(store.counter("n_sequences", txn) + 1), db=meta)
    txn.put(b"n_edges", u64(store.counter("n_edges", txn) + added), db=meta)
    txn.put(b"n_components", u64(n_components), db=meta)
    crash_point("add.before_commit")
    return store.uf.find(txn, record.seq_id), added
