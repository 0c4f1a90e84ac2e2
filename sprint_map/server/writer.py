"""CommitWriter: the single writer thread through which every commit goes, in order.

A commit is what ``SprintMap.ingest`` does at the end of a drive, through the same path
(:meth:`MapService.begin_drive <sprint_map.facade.service.MapService.begin_drive>`,
:meth:`DriveWriter.commit <sprint_map.merge.commit.DriveWriter.commit>`): the drive's descriptors and
the decisions the merge rule selects as edges, in one LMDB transaction. It is acknowledged (its future resolves) only after that transaction returned,
i.e. once durable (LMDB ``sync=True``). The slow part, writing and fsyncing the shard rows,
runs beside the frames (the rows are invisible until the transaction); only the transaction and
the index update hold the map gate exclusively.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Container, Iterator
from concurrent.futures import Future
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from sprint_map import AddResult, DriveWriter, FrameDecision
from sprint_map.map import SprintMap
from sprint_map.server.errors import busy
from sprint_map.server.gate import MapGate
from sprint_map.util.arrays import Descriptors

__all__ = ["CommitJob", "CommitOutcome", "CommitWriter", "JoinJob", "NameClaims"]

log = logging.getLogger("sprint_map.server")


@dataclass(frozen=True)
class CommitJob:
    """A drive to commit: its descriptors (in frame order) and the decisions it was answered.

    ``smoothed``, if given, re-makes the decisions from the whole drive (the session
    localizer's after-drive decisions, :meth:`SprintMap.smoothed <sprint_map.map.SprintMap.smoothed>`); the writer merges those,
    as ``ingest`` does, and calls it in its own thread, never in the event loop.
    """

    name: str | None
    descriptors: Descriptors
    decisions: list[FrameDecision]
    source: str = ""
    positions: np.ndarray | None = None  # (frames, 2..4) as ``ingest`` takes them
    smoothed: Callable[[], list[FrameDecision]] | None = None
    #: the session's centring: the commit stores the rows centred as they were searched
    centring: Any = None


@dataclass(frozen=True)
class JoinJob:
    """A join of another map's drives (:meth:`SprintMap.join <sprint_map.map.SprintMap.join>`)
    run by the writer: localised in its thread beside the frames, committed under the gate."""

    source: str
    options: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class CommitOutcome:
    """A durable commit: what the store committed and how long frames were held up.

    ``added`` is None for a drive of a ``novel``-admission map that stored no frame;
    ``frames`` is the drive's length, ``frames_stored`` the frames its sequence holds."""

    added: AddResult | None
    changed: frozenset[int]
    exclusive_s: float
    name: str = ""
    frames: int = 0
    frames_stored: int = 0

    @property
    def edges_added(self) -> int:
        return self.added.edges_added if self.added is not None else 0



class NameClaims(Protocol):
    """Where an unnamed drive's default name is chosen (the service's session registry)."""

    def begin_default(self, begin: Callable[[Container[str]], DriveWriter]
                      ) -> DriveWriter:
        """``begin(names in use)``, atomically with claiming the name it chose."""

    def release(self, name: str) -> None:
        """Give up a claimed name whose commit failed."""


class CommitWriter:
    """One thread committing :class:`CommitJob` s from a bounded queue.

    Parameters
    ----------
    smap : SprintMap
        The map, open for writing (shared with the frame workers).
    gate : MapGate
        Held exclusively around the commit's transaction.
    on_commit : callable
        Called with the changed component ids while the gate is still held exclusively (the
        registry tells the live filters), so no frame sees the new map before its filter knows.
    queue_size : int
        Commits that may wait; :meth:`submit` answers 503 beyond.
    names : NameClaims, optional
        The names held by drives not committed yet (the open sessions): an unnamed drive's
        sequence is begun through :meth:`NameClaims.begin_default`, so its default name avoids
        them as it avoids the map's names, and no session can take that name meanwhile.
    """

    def __init__(self, smap: SprintMap, gate: MapGate, on_commit: Callable[[set[int]], None],
                 queue_size: int, names: NameClaims | None = None) -> None:
        self.smap = smap
        self.gate = gate
        self.on_commit = on_commit
        self.names = names
        self._queue: queue.Queue[tuple[CommitJob | JoinJob, Future[Any]] | None] = \
            queue.Queue(maxsize=queue_size)
        self._thread = threading.Thread(target=self._run, name="sprint-map-writer", daemon=True)
        self._accepting = True

    @property
    def depth(self) -> int:
        """Commits waiting (not counting the one in progress)."""
        return self._queue.qsize()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def start(self) -> None:
        self._thread.start()

    def submit(self, job: CommitJob | JoinJob) -> Future[Any]:
        """Queue ``job``; the future resolves once the commit is durable (or failed): with a
        :class:`CommitOutcome` for a drive, the ``JoinResult`` for a join.

        Raises
        ------
        ApiError
            503 if the queue is full or the writer is stopping.
        """
        future: Future[Any] = Future()
        if not self._accepting:
            raise busy("the server is shutting down")
        try:
            self._queue.put_nowait((job, future))
        except queue.Full:
            raise busy(f"{self._queue.maxsize} commits are already waiting; retry later") from None
        return future

    def stop(self, timeout: float | None = None) -> None:
        """Commit what is queued, then end the thread."""
        self._accepting = False
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join(timeout)

    def _run(self) -> None:
        self._retrain_index()  # from now on, never inside a commit
        while True:
            item = self._queue.get()
            if item is None:  # stop
                return
            job, future = item
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(self.join(job) if isinstance(job, JoinJob)
                                  else self.commit(job))
            except BaseException as exc:  # the caller gets every failure, the thread goes on
                future.set_exception(exc)
            self._retrain_index()

    def _retrain_index(self) -> None:
        """Retrain the approximate index if the map outgrew it, beside the frames: only the
        switch to the new generation holds the gate (``SprintMap.service.retrain_index_beside``)."""
        try:
            if self.smap.service.retrain_index_beside(self.gate.exclusive):
                log.info("index trained again beside the sessions")
        except Exception:  # the commits are durable; the old index goes on answering
            log.exception("index retraining failed; the previous index is kept")

    def join(self, job: JoinJob) -> Any:
        """Join another map's drives (in the writer thread): its localisation reads the map
        beside the frames (only this thread changes it); the gate is held exclusively around
        its one transaction, the index's catch-up and the registry's update only."""
        return self.smap.join(job.source, exclusive=self.gate.exclusive,
                              on_commit=self.on_commit, **job.options)

    def commit(self, job: CommitJob) -> CommitOutcome:
        """Commit one drive (in the writer thread; also usable directly when no thread runs)."""
        smap = self.smap
        # The map changes only in this thread: the smoothing sees the map the commit extends.
        decisions = job.smoothed() if job.smoothed is not None else job.decisions
        if job.name is not None or self.names is None:
            begun = smap.service.begin_drive(job.name, job.source, centring=job.centring)
        else:
            begun = self.names.begin_default(
                lambda taken: smap.service.begin_drive(None, job.source, taken, job.centring))
        held = 0.0

        @contextmanager
        def exclusive() -> Iterator[None]:
            nonlocal held
            with self.gate.exclusive():
                start = time.perf_counter()
                yield
                held = time.perf_counter() - start

        try:
            with begun as drive:
                drive.append(job.descriptors)  # shards written; not yet visible
                # The rows fsynced, then under the exclusive gate the commit point (durable on
                # return) and the registry told.
                done = drive.commit(decisions, job.positions, exclusive=exclusive,
                                    on_commit=self.on_commit)
        except BaseException:
            if job.name is None and self.names is not None:
                self.names.release(begun.name)  # nothing was committed under it
            raise
        stored = done.added.sequence.length if done.added is not None else 0
        return CommitOutcome(done.added, done.changed, held, begun.name, done.frames, stored)
