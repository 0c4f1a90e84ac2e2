"""Committing one localised drive: its rows, then its merges as edges, in one atomic commit.

This is the one commit path of a localised drive. :meth:`SprintMap.ingest
<sprint_map.map.SprintMap.ingest>` streams the rows in while it localises them (and so does
``ingest_drives``, drive after drive), :meth:`SprintMap.merge <sprint_map.map.SprintMap.merge>`
hands them in whole, :meth:`SprintMap.commit_prepared
<sprint_map.map.SprintMap.commit_prepared>` commits a drive an ingest farm localised, and the
service's writer thread (:mod:`sprint_map.server.writer`) appends them beside the frames and
commits under its map gate; all of them end in :meth:`DriveWriter.commit`, which

1. runs the map's merge rule (:mod:`sprint_map.merge.rule`) over the drive's decisions and
   turns the selected ones into edges (:func:`merge_edges`, both ways if
   ``merge_both_ways``);
2. commits the sequence with those edges in one LMDB transaction (the commit point; see
   :mod:`sprint_map.storage.sequence_writer`), a retry of a drive already committed under its
   name with the same rows included (``AddResult.already_committed``).

A :class:`DriveWriter` left without a commit (or on any error) aborts: the rows it appended
are truncated away and nothing is half-visible.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from sprint_map.merge.rule import MergeRule, select_merges
from sprint_map.storage.records import AddResult, EdgeSpec
from sprint_map.storage.sequence_writer import SequenceWriter
from sprint_map.util.validation import validate_descriptors

if TYPE_CHECKING:  # the decisions' types; ``info`` and ``sequences`` load no HMM
    from sprint_map.localize.localizer import FrameDecision, Timing

__all__ = ["DriveCommit", "DriveWriter", "IngestResult", "merge_edges"]


@dataclass(frozen=True)
class IngestResult:
    """What :meth:`SprintMap.ingest <sprint_map.map.SprintMap.ingest>` did: the commit, the
    decisions that made its edges."""

    added: AddResult
    decisions: list[FrameDecision]
    timing: Timing
    #: The merge rule's verdict per decision: which became edges (empty without a merge).
    merged: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))

    def to_dict(self) -> dict[str, Any]:
        seq = self.added.sequence
        merged = self.merged.tolist() if len(self.merged) else [False] * len(self.decisions)
        return {
            "seq_id": seq.seq_id,
            "name": seq.name,
            "frames": seq.length,
            "component": self.added.component,
            "edges_added": self.added.edges_added,
            # a retry of a drive committed under this name with these very descriptors
            "already_committed": self.added.already_committed,
            "decisions": [{**d.to_dict(), "merged": m}
                          for d, m in zip(self.decisions, merged, strict=True)],
            "timing": self.timing.to_dict(),
        }


@dataclass(frozen=True)
class DriveCommit:
    """What :meth:`DriveWriter.commit` committed.

    ``merged`` is the merge rule's verdict per decision (which became edges); ``changed`` the
    components the commit changed: the new sequence's and those its edges joined into it (as
    they were before the commit), for a cache of components to invalidate.
    """

    added: AddResult
    merged: np.ndarray
    changed: frozenset[int]


class DriveWriter:
    """One drive being written into a map open for writing; use as a context manager.

    Made by :meth:`SprintMap.begin_drive <sprint_map.map.SprintMap.begin_drive>`. Rows go to the
    map's shards as they are appended, invisible to readers until :meth:`commit`.

    Parameters
    ----------
    writer : SequenceWriter
        The storage layer's writer of the new sequence.
    rule : MergeRule
        The map's merge rule.
    both_ways : bool
        Store each merge edge in both directions (the map's ``merge_both_ways``).
    component_of : callable
        The component id of a sequence of the map (for :attr:`DriveCommit.changed`).
    """

    def __init__(self, writer: SequenceWriter, rule: MergeRule, both_ways: bool,
                 component_of: Callable[[int], int]) -> None:
        self._writer = writer
        self._rule = rule
        self._both_ways = both_ways
        self._component_of = component_of

    @property
    def name(self) -> str:
        """The new sequence's name (the default one chosen if none was given)."""
        return self._writer.name

    @property
    def frames(self) -> int:
        """Rows appended so far."""
        return self._writer.frames

    def __enter__(self) -> DriveWriter:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        self._writer.__exit__(exc_type, *exc)

    def append(self, rows: Any) -> None:
        """Write a batch of descriptor rows (validated, fsynced, not yet visible). O(n * dim)."""
        self._writer.append(rows)

    def abort(self) -> None:
        """Drop every row appended so far; nothing is committed."""
        self._writer.abort()

    def commit(
        self,
        decisions: Sequence[FrameDecision],
        positions: Any = None,
        *,
        rows: Any = None,
        thumbnails: Sequence[bytes] | None = None,
        exclusive: Callable[[], AbstractContextManager[Any]] | None = None,
        on_commit: Callable[[set[int]], None] | None = None,
    ) -> DriveCommit:
        """Commit the drive with the decisions the merge rule selects as edges, atomically.

        ``decisions``: the drive's localisation decisions (usually smoothed; empty for a drive
        committed without localisation). ``positions``: per-frame ``x, y[, heading_deg[, time[,
        sigma_m]]]``. ``rows``: the drive's rows if not appended yet (validated, with the positions
        and edges, before the first row is written). ``thumbnails``: one JPEG per frame.
        ``exclusive``: a context manager factory held around the LMDB transaction and ``on_commit``
        only (the service's map gate). ``on_commit``: called with :attr:`DriveCommit.changed` right
        after the transaction, inside ``exclusive``.

        Notes
        -----
        O(D) for the merge rule over D decisions, plus the commit: O(N * dim) shard I/O (for
        ``rows``), O(N) LMDB puts and O(E log n) for the edges and their unions.
        """
        merged = select_merges(decisions, self._rule)
        edges = merge_edges(decisions, merged, self._both_ways)
        before: set[int] = set()
        if on_commit is not None:
            # Only the map's one writer changes the union-find, so these roots hold until the
            # commit.
            before = {self._component_of(seq)
                      for seq in {s for e in edges for s, _ in (e.src, e.dst) if s is not None}}
        writer = self._writer
        if rows is not None:
            if writer.frames:
                raise ValueError("rows given to commit after rows were appended")
            rows = validate_descriptors(rows, writer.store.config.dim)
            writer.prepare(positions, edges, len(rows))  # nothing is written for bad input
            writer.append(rows)
        if exclusive is not None:
            writer.sync()  # the rows' fsync, the slow part, before the gate: not under it
        with exclusive() if exclusive is not None else nullcontext():
            added = writer.commit(positions, edges, thumbnails)
            changed = before | {added.component}
            if on_commit is not None:
                on_commit(changed)
        return DriveCommit(added, merged, frozenset(changed))


def merge_edges(decisions: Sequence[FrameDecision], merged: np.ndarray, both_ways: bool
                ) -> list[EdgeSpec]:
    """The edges that merging a localised drive adds: one per merged decision.

    ``merged`` is the merge rule's verdict per decision
    (:func:`sprint_map.merge.rule.select_merges`). A merged decision on frame ``i`` matched to
    ``(s, j)`` gives the edge ``(new, i) -> (s, j)`` with weight ``min(prob, 1)``, and with
    ``both_ways`` also ``(s, j) -> (new, i)``, so that belief can later cross from the old drive
    into the new one as well as back.
    """
    edges = []
    for d, keep in zip(decisions, np.asarray(merged, dtype=bool).tolist(), strict=True):
        if not keep or d.seq_id is None or d.image_id is None:
            continue
        weight = min(1.0, float(d.prob))
        edges.append(EdgeSpec((None, d.frame), (d.seq_id, d.image_id), weight, d.frame))
        if both_ways:
            edges.append(EdgeSpec((d.seq_id, d.image_id), (None, d.frame), weight, d.frame))
    return edges
