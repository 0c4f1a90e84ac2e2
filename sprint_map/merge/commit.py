"""Committing one localised drive: its rows, then its merges as edges, in one atomic commit.

This is the one commit path of a localised drive. :meth:`SprintMap.ingest
<sprint_map.map.SprintMap.ingest>` streams the rows in while it localises them (and so does
``ingest_drives``, drive after drive), :meth:`SprintMap.merge <sprint_map.map.SprintMap.merge>`
hands them in whole, :meth:`MapService.commit_prepared
<sprint_map.facade.service.MapService.commit_prepared>` commits a drive an ingest farm localised,
and the service's writer thread (:mod:`sprint_map.server.writer`) appends them beside the frames and
commits under its map gate; all of them end in :meth:`DriveWriter.commit`, which

1. runs the map's merge rule (:mod:`sprint_map.merge.rule`) over the drive's decisions and
   turns the selected ones into edges (:func:`merge_edges`, both ways if
   ``merge_both_ways``);
2. with the map's admission ``novel``, keeps only the frames the map lacks
   (:mod:`sprint_map.merge.admission`): their rows, positions and thumbnails, their merge
   edges, the edges stitching each stored run into the map, and a sighting of each place the
   other frames matched. Such a drive's rows are held in memory until the commit (the rows to
   store are known only once the whole drive is decided); a drive with nothing to store
   commits its sightings alone and no sequence (:attr:`DriveCommit.added` None);
3. commits the sequence with those edges in one LMDB transaction (the commit point; see
   :mod:`sprint_map.storage.sequence_writer`), a retry of a drive already committed under its
   name with the same rows included (``AddResult.already_committed``).

A :class:`DriveWriter` left without a commit (or on any error) aborts: the rows it appended
are truncated away and nothing is half-visible.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from sprint_map.errors import UnknownSequenceError
from sprint_map.merge.admission import (
    COPY_STEPS,
    Admission,
    AdmissionPlan,
    drive_step,
    place_distances,
    plan_admission,
)
from sprint_map.merge.rule import MergeRule, select_merges
from sprint_map.storage.records import AddResult, EdgeSpec
from sprint_map.storage.sequence_writer import SequenceWriter
from sprint_map.util.validation import validate_descriptors

if TYPE_CHECKING:  # the decisions' types; ``info`` and ``sequences`` load no HMM
    from sprint_map.frontend.centring import DriveCentring
    from sprint_map.localize.localizer import FrameDecision, Timing

__all__ = ["DriveCommit", "DriveWriter", "IngestResult", "merge_edges"]


@dataclass(frozen=True)
class IngestResult:
    """What :meth:`SprintMap.ingest <sprint_map.map.SprintMap.ingest>` did: the commit, the
    decisions that made its edges.

    ``added`` is None for a drive of a ``novel``-admission map that stored no frame (its
    sightings were committed); ``name`` is the drive's name either way, ``frames`` its length.
    """

    added: AddResult | None
    decisions: list[FrameDecision]
    timing: Timing
    #: The merge rule's verdict per decision: which became edges (empty without a merge).
    merged: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    #: Each frame's image id in the new sequence, -1 where it was not stored (empty: all were).
    image_of: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    name: str = ""
    frames: int = 0
    sightings: int = 0

    @property
    def edges_added(self) -> int:
        return self.added.edges_added if self.added is not None else 0

    @property
    def frames_stored(self) -> int:
        if not len(self.image_of):
            return self.frames
        return int((self.image_of >= 0).sum())

    def stored_as(self, frame: int) -> tuple[int, int] | None:
        """``(seq_id, image_id)`` of the vertex frame ``frame`` became, or None."""
        if self.added is None:
            return None
        image = int(self.image_of[frame]) if len(self.image_of) else frame
        return None if image < 0 else (self.added.sequence.seq_id, image)

    def to_dict(self) -> dict[str, Any]:
        added = self.added
        merged = self.merged.tolist() if len(self.merged) else [False] * len(self.decisions)
        stored = [self.stored_as(d.frame) for d in self.decisions]
        return {
            "seq_id": added.sequence.seq_id if added is not None else None,
            "name": added.sequence.name if added is not None else self.name,
            "frames": self.frames,
            "frames_stored": self.frames_stored,
            "frames_skipped": self.frames - self.frames_stored,
            "sightings": self.sightings,
            "component": added.component if added is not None else None,
            "edges_added": self.edges_added,
            # a retry of a drive committed under this name with these very descriptors
            "already_committed": added.already_committed if added is not None else False,
            "decisions": [{**d.to_dict(), "merged": m,
                           "stored_as": list(s) if s is not None else None}
                          for d, m, s in zip(self.decisions, merged, stored, strict=True)],
            "timing": self.timing.to_dict(),
        }


@dataclass(frozen=True)
class DriveCommit:
    """What :meth:`DriveWriter.commit` committed.

    ``added`` is None when admission stored no frame of the drive; ``merged`` is the merge
    rule's verdict per decision (which became edges); ``changed`` the components the commit
    changed: the new sequence's and those its edges joined into it (as they were before the
    commit), for a cache of components to invalidate; ``plan`` what admission stored of the
    drive (every frame with ``"all"``); ``frames`` the drive's length.
    """

    added: AddResult | None
    merged: np.ndarray
    changed: frozenset[int]
    plan: AdmissionPlan | None = None
    frames: int = 0
    sightings: int = 0

    def result(self, decisions: list[FrameDecision], timing: Timing, name: str
               ) -> IngestResult:
        """The :class:`IngestResult` of this commit."""
        image_of = self.plan.image_of if self.plan is not None else np.zeros(0, dtype=np.int64)
        return IngestResult(self.added, decisions, timing, self.merged, image_of, name,
                            self.frames, self.sightings)


class DriveWriter:
    """One drive being written into a map open for writing; use as a context manager.

    Made by :meth:`MapService.begin_drive <sprint_map.facade.service.MapService.begin_drive>`.
    Rows go to the map's shards as they are appended, invisible to readers until
    :meth:`commit` (with admission ``novel`` they are held in memory until then: which ones
    are stored is known only at the commit).

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
    admission : Admission
        Which frames are stored (:mod:`sprint_map.merge.admission`; default every one).
    centring : DriveCentring, optional
        The drive's centring (:mod:`sprint_map.frontend.centring`): rows are given as
        described and stored centred, and its statistics are committed with the sequence.
        None: rows are stored as given, with no statistics.
    """

    def __init__(self, writer: SequenceWriter, rule: MergeRule, both_ways: bool,
                 component_of: Callable[[int], int], admission: Admission | None = None,
                 centring: DriveCentring | None = None) -> None:
        self._writer = writer
        self.centring = centring
        self._rule = rule
        self._both_ways = both_ways
        self._component_of = component_of
        self._admission = admission if admission is not None else Admission()
        #: rows held until the commit (admission ``novel``)
        self._held: list[np.ndarray] | None = [] if self._admission.mode != "all" else None
        self._held_frames = 0

    @property
    def name(self) -> str:
        """The new sequence's name (the default one chosen if none was given)."""
        return self._writer.name

    @property
    def frames(self) -> int:
        """Rows appended so far."""
        return self._held_frames if self._held is not None else self._writer.frames

    def __enter__(self) -> DriveWriter:
        return self

    def __exit__(self, exc_type: object, *exc: object) -> None:
        self._writer.__exit__(exc_type, *exc)

    def append(self, rows: Any) -> np.ndarray:
        """Write a batch of the drive's descriptor rows (validated, then centred, fsynced, not
        yet visible); returns them as stored: the rows to localise. O(n * dim)."""
        batch = validate_descriptors(rows, self._writer.store.config.dim, self.frames)
        if self.centring is not None:
            batch = self.centring.apply(batch)
        if self._held is None:
            self._writer.append(batch)
            return batch
        self._held.append(batch)
        self._held_frames += len(batch)
        return batch

    def abort(self) -> None:
        """Drop every row appended so far; nothing is committed."""
        if self._held is not None:
            self._held.clear()
            self._held_frames = 0
        self._writer.abort()

    def _place_distances(self, rows: np.ndarray, decisions: Sequence[FrameDecision],
                         merged: np.ndarray) -> tuple[np.ndarray, float, np.ndarray | None]:
        """Each merged frame's squared distance to its place's stored views (or to a copy of
        the frame one edge away, or to its best retrieval hit if that is a copy; for another
        frame, to such a copy only), the drive's step
        (:func:`sprint_map.merge.admission.place_distances`) and each frame's squared distance
        to its best hit (None without a step), read in one LMDB transaction.
        O(n * dim) row reads, and one edge range read per matched frame that is no copy of its
        decided place's views or its best hit."""
        store = self._writer.store
        lengths: dict[int, tuple[int, int]] = {}
        with store.env.read() as txn:
            total = store.counter("next_vertex_id", txn)

            def span(seq_id: int) -> tuple[int, int]:
                if seq_id not in lengths:
                    try:
                        rec = store.sequence(seq_id, txn)
                        lengths[seq_id] = (rec.first_vertex, rec.length)
                    except UnknownSequenceError:  # removed since the drive was localised
                        lengths[seq_id] = (0, 0)
                return lengths[seq_id]

            def read(seq_id: int, start: int, stop: int) -> np.ndarray:
                first = span(seq_id)[0]
                return store.shards.rows(first + start, first + stop, total)

            def linked(seq_id: int, start: int, stop: int) -> list[tuple[int, int]]:
                first, length = span(seq_id)
                ends = {e.dst for e in store.edges_from(first + start,
                                                        first + min(stop, length) - 1, txn)}
                try:
                    return store.locate(sorted(ends), txn)
                except UnknownSequenceError:  # an end removed meanwhile: no copy looked for
                    return []

            def hit_distances() -> np.ndarray:
                """Each frame's squared distance to its best hit's stored row (inf without a
                hit, or where it was removed since the drive was localised)."""
                ids = np.array([-1 if d.nearest is None else d.nearest for d in decisions],
                               dtype=np.int64)
                live = (ids >= 0) & (ids < total)
                live[live] &= ~store.removed_ranges(txn).contains(ids[live])
                out = np.full(len(ids), np.inf)
                diff = store.shards.take(ids[live], total) - rows[live]
                out[live] = np.einsum("ij,ij->i", diff, diff)
                return out

            step = drive_step(rows)
            copy_limit = COPY_STEPS * step if math.isfinite(step) else 0.0
            copies = hit_distances() if copy_limit > 0 else None
            return (place_distances(rows, decisions, merged, read, lambda s: span(s)[1],
                                    linked=linked, copy_limit=copy_limit, copies=copies), step,
                    copies)

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
        O(D) for the merge rule and admission over D decisions, plus the commit: O(N * dim)
        shard I/O (for ``rows``, or the rows held), O(N) LMDB puts and O(E log n) for the edges
        and their unions.
        """
        merged = select_merges(decisions, self._rule)
        writer = self._writer
        if rows is not None:
            if self.frames:
                raise ValueError("rows given to commit after rows were appended")
            rows = validate_descriptors(rows, writer.store.config.dim)
            if self.centring is not None:
                rows = self.centring.apply(rows)
        admit = self._held is not None and len(decisions) > 0
        plan = None
        if admit:
            if rows is None:
                rows = (np.concatenate(self._held) if self._held
                        else np.zeros((0, writer.store.config.dim), dtype=np.float32))
            if len(decisions) != len(rows):
                raise ValueError(f"{len(decisions)} decisions for a drive of {len(rows)} frames")
            plan = plan_admission(decisions, merged, self._admission, self._both_ways,
                                  *self._place_distances(rows, decisions, merged))
            edges = plan.edges
            frames = len(rows)
            rows = plan.select(rows)
            positions = plan.select(None if positions is None else np.asarray(positions))
            thumbnails = plan.select(thumbnails)  # type: ignore[assignment]
            sightings = plan.sightings
        else:
            if rows is None and self._held is not None:  # not localised: every frame
                rows = np.concatenate(self._held) if self._held else None
            edges = merge_edges(decisions, merged, self._both_ways)
            sightings = []
            frames = len(rows) if rows is not None else writer.frames
        before: set[int] = set()
        if on_commit is not None:
            # Only the map's one writer changes the union-find, so these roots hold until the
            # commit.
            before = {self._component_of(seq)
                      for seq in {s for e in edges for s, _ in (e.src, e.dst) if s is not None}}
        if plan is not None and plan.frames_stored == 0:
            writer.abort()  # nothing to store: the sightings alone are committed
            with exclusive() if exclusive is not None else nullcontext():
                counted = writer.store.record_sightings(writer.name, sightings)
                if on_commit is not None:
                    on_commit(set())
            return DriveCommit(None, merged, frozenset(), plan, frames, counted)
        if rows is not None:
            writer.prepare(positions, edges, len(rows))  # nothing is written for bad input
            writer.append(rows)
        if exclusive is not None:
            writer.sync()  # the rows' fsync, the slow part, before the gate: not under it
        if self.centring is not None and self.centring.frames:
            writer.set_stats(self.centring.stats.frames, self.centring.stats.mean)
        with exclusive() if exclusive is not None else nullcontext():
            added = writer.commit(positions, edges, thumbnails, sightings)
            changed = before | {added.component}
            if on_commit is not None:
                on_commit(changed)
        return DriveCommit(added, merged, frozenset(changed), plan, frames, len(sightings))


def merge_edges(decisions: Sequence[FrameDecision], merged: np.ndarray, both_ways: bool
                ) -> list[EdgeSpec]:
    """The edges that merging a localised drive adds: one per merged decision.

    ``merged`` is the merge rule's verdict per decision
    (:func:`sprint_map.merge.rule.select_merges`). A merged decision on frame ``i`` matched to
    ``(s, j)`` gives the edge ``(new, i) -> (s, j)`` with weight ``min(prob, 1)``, and with
    ``both_ways`` also ``(s, j) -> (new, i)``, so that belief can later cross from the old drive
    into the new one as well as back.
    """
    return plan_admission(decisions, merged, Admission(), both_ways).edges
