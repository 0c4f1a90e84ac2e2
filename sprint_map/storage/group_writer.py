"""Several new sequences committed together: one fsync of their rows, one LMDB transaction.

A lone sequence (:class:`~sprint_map.storage.sequence_writer.SequenceWriter`) pays a fixed
cost at its commit: an fsync of the shard files its rows went to, and LMDB's commit (an
fdatasync of the pages, then the meta page written synchronously). A :class:`GroupWriter`
pays it once for a whole group of sequences that need not see each other before they are
committed (drives appended without localisation: ``sprint-map ingest MAP A B C --no-merge``):

1. each sequence's rows are written to the shards after the previous one's, uncommitted, and
   its records (name, positions, edges, thumbnails) validated as it is added (:meth:`add`);
   a sequence that fails (bad rows, bad records, a name taken) has its rows truncated and is
   left out; the ones added before it stay in the group;
2. :meth:`commit`: one fsync of every shard file the group wrote (crash point
   ``group.rows_written``), then one LMDB transaction recording every sequence of the group in
   order (``group.before_commit`` inside it): **the group's commit point**; then the index
   catches up with all of them at once (``group.committed`` before that).

Each sequence is still atomic: the transaction holds whole sequences only, each validated
before the transaction begins, so a kill before the commit point leaves none of the group (its
rows lie past the committed end of the shards and the next writer's open truncates them) and a
kill after it all of them. Edges may join a sequence to an earlier one of the same group. A
retry of a sequence committed under the same name with the same rows is recognised as it is
added (``AddResult.already_committed``) and writes nothing, as for a lone sequence.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

from sprint_map.errors import SprintMapError
from sprint_map.storage.records import AddResult, EdgeSpec, SequenceRecord
from sprint_map.storage.sequence_writer import (
    SequenceWriter,
    StagedSequence,
    UncommittedRows,
    WritableMap,
    write_staged,
)
from sprint_map.testing.crash import crash_point

__all__ = ["GroupWriter"]


class GroupWriter(UncommittedRows):
    """Sequences added one after the other, committed in one transaction; a context manager.

    Holds the map's writing slot from its creation to its commit or abort (no other sequence
    can be written meanwhile). Leaving the ``with`` block without :meth:`commit`, or on an
    error, aborts: every row of the group is truncated away and nothing is committed.

    Parameters
    ----------
    store : WritableMap
        A map open for writing (a ``MapStore``).
    """

    def __init__(self, store: WritableMap) -> None:
        store.require_writer()
        if store.writing is not None:
            raise SprintMapError("another sequence is already being written to this map")
        with store.env.read() as txn:
            #: The first vertex id of the group: its rows start here, past the committed end.
            self.first = store.counter("next_vertex_id", txn)
        self.store = store
        #: In the order added: staged sequences, and retries' results (nothing to write).
        self._added: list[StagedSequence | AddResult] = []
        self._done = False
        store.start_writing(self)

    @property
    def staged(self) -> list[SequenceRecord]:
        """The records of the sequences the group will commit, in order (retries excluded)."""
        return [s.record for s in self._added if isinstance(s, StagedSequence)]

    @property
    def digests(self) -> list[bytes]:
        """The content digests of :attr:`staged`'s rows, in order."""
        return [s.digest for s in self._added if isinstance(s, StagedSequence)]

    @property
    def frames(self) -> int:
        """Rows the group has written (uncommitted)."""
        return sum(r.length for r in self.staged)

    def __len__(self) -> int:
        """Sequences added (retries included)."""
        return len(self._added)

    def add(self, rows: Any | Iterable[Any], name: str | None = None, source: str = "",
            positions: Any = None, edges: Sequence[EdgeSpec] = (),
            thumbnails: Sequence[bytes] | None = None,
            stats: Callable[[], tuple[int, np.ndarray]] | None = None) -> None:
        """Write one sequence's rows after the group's, uncommitted, and stage its records.

        Parameters
        ----------
        rows : array_like (N, dim), or an iterable of (n_i, dim) batches
            An array is validated whole (with positions and edges) before a row is written;
            batches one at a time (memory: one batch), the records after the last.
        name, source, positions, edges, thumbnails
            As for :meth:`sprint_map.storage.store.MapStore.add_sequence`; ``name`` unique in
            the group, ``edges`` may reach its earlier sequences; thumbnails read last.
        stats : callable, optional
            Called after the last batch: the drive's ``(frames, mean)``
            (:mod:`sprint_map.storage.drive_stats`).

        Raises
        ------
        Any error of ``add_sequence``
            Nothing of this sequence is kept (its rows are truncated); the sequences added
            before it stay in the group.

        Notes
        -----
        O(N * dim) rows (fsynced once for the group by :meth:`commit`), O(N + E) records.
        """
        if self._done:
            raise SprintMapError("the group was already committed or aborted")
        writer = SequenceWriter(self.store, name, source, follows=self.staged)
        with writer:  # an error (or a batch iterator's) drops this sequence's rows
            if isinstance(rows, np.ndarray):
                if rows.ndim == 2 and len(rows):  # (else append refuses them, unwritten)
                    writer.prepare(positions, edges, len(rows))  # nothing written if bad
                writer.append(rows)  # validated whole before it is written
            else:
                for batch in rows:
                    writer.append(batch)
            if stats is not None:
                writer.set_stats(*stats())
            self._added.append(writer.stage(positions, edges, thumbnails))

    def commit(self, extra: Callable[[Any], None] | None = None) -> list[AddResult]:
        """Make the group's rows durable (one fsync per shard file written), then record every
        sequence of the group in one LMDB transaction: the commit point. Returns one result per
        sequence added, in order. ``extra``, if given, writes more records into the same
        transaction after the sequences' (a join's copied records, :mod:`sprint_map.storage.
        join`); like the body it may be run again in a new transaction (a full map grows).

        Raises
        ------
        StorageIOError
            The rows cannot be fsynced, or the transaction fails: nothing of the group is
            committed (its rows are truncated).

        Notes
        -----
        Two fsync barriers in all (the shard files', LMDB's commit) however many sequences,
        plus O(sum of N + E) LMDB puts in the one transaction; then the index catches up with
        the group's rows at once (a failure there is only a warning: the rows are committed).
        """
        if self._done:
            raise SprintMapError("the group was already committed or aborted")
        staged = [s for s in self._added if isinstance(s, StagedSequence)]
        written: list[tuple[int, int]] = []
        try:
            if staged:
                self.store.shards.sync()  # every row is durable before the commit counting it
                crash_point("group.rows_written")

                def body(txn: Any) -> list[tuple[int, int]]:
                    out = [write_staged(self.store, txn, s) for s in staged]
                    if extra is not None:
                        extra(txn)
                    crash_point("group.before_commit")
                    return out

                written = self.store.env.write(body)
        except BaseException:
            self._rollback_after_error()
            raise
        self._done = True
        self.store.end_writing(self)
        if not staged:
            return [s for s in self._added if isinstance(s, AddResult)]
        crash_point("group.committed")
        frames = sum(s.record.length for s in staged)
        try:
            self.store.after_commit(self.first, frames)
        except Exception as exc:  # committed and durable: the index is a cache of them
            self.store.warnings.append(
                f"{len(staged)} sequence(s) committed, but the index cache was not updated "
                f"({exc}); rebuilt when needed")
        results = iter(AddResult(s.record, component, added)
                       for s, (component, added) in zip(staged, written, strict=True))
        return [a if isinstance(a, AddResult) else next(results) for a in self._added]

    def drop_rows(self) -> None:
        """Drop every row the group wrote (see :meth:`abort`)."""
        self.store.end_writing(self)
        if self.staged:
            self.store.shards.recover(self.first)
