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

import hashlib
import time
from collections.abc import Callable, Container, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from sprint_map.errors import (
    DuplicateNameError,
    EmptySequenceError,
    MapCorruptError,
    SprintMapError,
    StorageIOError,
)
from sprint_map.storage.crash import crash_point
from sprint_map.storage.keys import DIGEST_BYTES, read_u32, u32
from sprint_map.storage.records import SequenceRecord
from sprint_map.storage.thumbnails import put_thumbnails, validate_thumbnails
from sprint_map.storage.validation import (
    validate_descriptors,
    validate_name,
    validate_positions,
)

if TYPE_CHECKING:
    from sprint_map.storage.records import AddResult, EdgeSpec
    from sprint_map.storage.store import MapStore, ResolvedEdge


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


class SequenceWriter:
    """Writes one new sequence into ``store``; use as a context manager.

    Parameters
    ----------
    store : MapStore
        A map open for writing; one sequence may be in progress at a time.
    name : str, optional
        Unique sequence name; checked now, before any row is written. The default is
        ``seq-<id>``, or the first of ``seq-<id>-2``, ``seq-<id>-3``, ... that no sequence of
        the map has and ``reserved`` does not hold (:func:`default_name`): a default never
        collides.
    source : str
        Free text recording where the sequence came from.
    reserved : container of str
        Names a default must also avoid (e.g. the service's sessions not committed yet).
    """

    def __init__(self, store: MapStore, name: str | None = None, source: str = "",
                 reserved: Container[str] = ()) -> None:
        store.require_writer()
        if store.writing is not None:
            raise SprintMapError("another sequence is already being written to this map")
        with store.env.read() as txn:
            self.seq_id = store.counter("next_seq_id", txn)
            self.first = store.counter("next_vertex_id", txn)
            names = store.env.db("seq_names")
            if name is None:
                self.name = default_name(self.seq_id, lambda candidate: candidate in reserved
                                         or txn.get(candidate.encode(), db=names) is not None)
            else:
                self.name = name
            validate_name(self.name)
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
        self._hash = hashlib.blake2b(digest_size=DIGEST_BYTES)
        self.source = source
        self.frames = 0
        self._lengths: dict[int, int] = {}
        self._done = False
        store._writing = self

    def __enter__(self) -> SequenceWriter:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        if not self._done:
            if exc_type is None:
                self.abort()
            else:
                self._rollback_after_error()

    def prepare(self, positions: Any, edges: Sequence[EdgeSpec], frames: int
                ) -> tuple[np.ndarray | None, list[ResolvedEdge]]:
        """Validate positions and edges for a sequence of ``frames`` frames (writes nothing)."""
        pos = validate_positions(positions, frames)
        lengths: dict[int, tuple[int, int]] = {}  # one sequence read per distinct sequence
        with self.store.env.read() as txn:
            resolved = [
                self.store._resolve_edge(e, self.seq_id, self.first, frames, txn, lengths)
                for e in edges
            ]
        return pos, resolved

    def append(self, rows: Any) -> None:
        """Write a batch of descriptor rows (validated; fsynced; not yet visible)."""
        if self._done:
            raise SprintMapError("the sequence was already committed or aborted")
        arr = np.asarray(rows)
        if arr.ndim == 2 and arr.shape[0] == 0:
            return
        try:
            arr = validate_descriptors(arr, self.store.config.dim, first_frame=self.frames)
            self._hash.update(arr.astype("<f4", copy=False).data)
            if self.retry_of is None:  # a possible retry writes nothing until it is decided
                self._lengths.update(self.store.shards.append(self.first + self.frames, arr))
        except BaseException:
            self._rollback_after_error()
            raise
        self.frames += len(arr)

    def commit(self, positions: Any = None, edges: Sequence[EdgeSpec] = (),
               thumbnails: Sequence[bytes] | None = None) -> AddResult:
        """Record the sequence with its positions, edges and thumbnails in one LMDB transaction.

        ``thumbnails``, if given, are one JPEG per frame (see
        :mod:`sprint_map.storage.thumbnails`); they are read here, at the commit, so a list a
        frame source fills while its batches stream is complete by then.

        Raises
        ------
        EmptySequenceError
            If no row was appended. Any error aborts the sequence (nothing is committed).
        InputError
            Thumbnails not one per frame, or not JPEG bytes.
        """
        from sprint_map.storage.records import AddResult

        try:
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
            crash_point("add.shards_written")

            def body(txn: Any) -> tuple[int, int]:
                txn.put(u32(record.seq_id), digest, db=self.store.env.db("digests"))
                if thumbs is not None:
                    put_thumbnails(txn, self.store.env, record.seq_id, thumbs)
                    crash_point("add.thumbnails_written")
                return self.store._commit(txn, record, self._lengths, pos, resolved)

            component, added = self.store.env.write(body)
        except BaseException:
            self._rollback_after_error()
            raise
        self._done = True
        self.store._writing = None
        crash_point("add.committed")
        try:
            self.store._after_commit(self.first, self.frames)
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
        from sprint_map.storage.records import AddResult

        assert self.retry_of is not None
        record, committed = self.retry_of
        if self.frames != record.length or digest != committed:
            raise DuplicateNameError(
                f"a sequence named {self.name!r} already exists with other descriptors "
                f"({record.length} frames; choose another name)")
        self._done = True
        self.store._writing = None
        self.store.warnings.append(
            f"sequence {record.name!r} was already committed with these very descriptors (as "
            f"sequence {record.seq_id}): nothing added")
        return AddResult(record, self.store.component_of(record.seq_id), 0,
                         already_committed=True)

    def abort(self) -> None:
        """Drop every row appended so far (truncate the shards to the committed length).

        Raises
        ------
        StorageIOError
            If the shards cannot be truncated; the rows stay invisible (LMDB never counted
            them) and the next writer's open truncates them.
        """
        if self._done:
            return
        self._done = True
        self.store._writing = None
        if self.retry_of is None:  # a possible retry wrote no row
            self.store.shards.recover(self.first)

    def _rollback_after_error(self) -> None:
        """:meth:`abort` while an error propagates: a failed rollback must not mask the error."""
        try:
            self.abort()
        except (StorageIOError, MapCorruptError) as exc:
            self.store.warnings.append(f"uncommitted rows not yet removed ({exc})")
