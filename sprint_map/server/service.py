"""LocalisationService: sessions, frame workers and the commit writer over one open map.

Threads: the event loop (uvicorn) admits requests and keeps per-session order; ``frame_workers``
threads answer frames (decode, describe, k-NN retrieval, HMM step) under the map gate's shared
side; one writer thread commits drives (:mod:`sprint_map.server.writer`). Every queue is
bounded: a full one answers 429 (one session too far ahead) or 503 (the server), never grows.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import gc
import logging
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

import anyio
import numpy as np

from sprint_map import LaggedLocalizer, Localizer, validate_lag
from sprint_map.errors import SprintMapError
from sprint_map.map import SprintMap
from sprint_map.server.batcher import FrameBatcher
from sprint_map.server.config import ServerConfig
from sprint_map.server.errors import ApiError, busy, from_library, unknown_session
from sprint_map.server.gate import MapGate
from sprint_map.server.heap import GcPauses, settle
from sprint_map.server.metrics import Metrics
from sprint_map.server.payloads import (
    JSON_TYPES,
    RAW_TYPE,
    descriptor_from_image,
    descriptor_from_json,
    descriptor_from_raw,
    media_type,
    parse_json,
    position_from_json,
    session_name,
)
from sprint_map.server.sessions import (
    CLOSED,
    COMMITTING,
    OPEN,
    Session,
    SessionRegistry,
)
from sprint_map.server.writer import CommitJob, CommitOutcome, CommitWriter, JoinJob

__all__ = ["LocalisationService"]

#: The fields of a frame's answer besides its timing (``FrameAnswer`` in the schema).
_ANSWER_FIELDS = ("frame", "seq_id", "image_id", "prob")
#: A lagged session's answer while no frame is old enough to be answered.
_NONE_YET: dict[str, Any] = dict.fromkeys(_ANSWER_FIELDS)

log = logging.getLogger("sprint_map.server")


class LocalisationService:
    """The service behind the HTTP routes (usable without HTTP, e.g. in tests).

    Parameters
    ----------
    smap : SprintMap
        A map open for writing; the service closes it on :meth:`shutdown` if ``owns_map``.
    config : ServerConfig
        Limits and settings.
    settle_heap : bool
        Once started, freeze the process's heap out of the garbage collector's later
        collections (:func:`sprint_map.server.heap.settle`): for a process that is the server
        (``sprint-map serve``), not one that creates services in passing (tests).
    """

    def __init__(self, smap: SprintMap, config: ServerConfig, *, owns_map: bool = True,
                 localizers: Callable[[], Any] | None = None,
                 settle_heap: bool = False) -> None:
        self.map = smap
        self.settle_heap = settle_heap
        #: Makes each session's localiser (default: in this process; ``serve --ray``: a proxy
        #: of one in a Ray replica, see sprint_map/fleet/replicas.py).
        self.localizers = localizers
        self.config = config
        self.owns_map = owns_map
        self.gate = MapGate()
        self.metrics = Metrics()
        self.registry = SessionRegistry(config.max_sessions, config.max_frames_per_session,
                                        config.max_buffered_bytes)
        self.cache = smap.service.shared_cache()
        self.writer = CommitWriter(smap, self.gate, self._changed, config.commit_queue_size,
                                   self.registry)
        #: Frames of all sessions searched together; None: each alone (batch_max_frames 0,
        #: or the sessions' localisers live in Ray replicas, which search their own frames).
        self.batcher = (FrameBatcher(smap, self.gate, smap.config.hmm.k,
                                     config.batch_window_ms / 1e3, config.batch_max_frames,
                                     config.search_threads)
                        if config.batch_max_frames and localizers is None else None)
        self.spec = smap.config.descriptor_spec()
        self.dim = smap.config.dim
        self.ready = False
        self.closing = False
        self._admitted = 0  # frame requests admitted, all sessions
        self._limiter: anyio.CapacityLimiter | None = None
        self._expiry: asyncio.Task[None] | None = None
        m = self.metrics
        m.gauge("sprint_map_sessions_active", "Open sessions.", lambda: len(self.registry))
        m.gauge("sprint_map_frames_queued", "Frame requests admitted (waiting or running).",
                lambda: self._admitted)
        m.gauge("sprint_map_commit_queue_depth", "Commits waiting for the writer.",
                lambda: self.writer.depth)
        m.gauge("sprint_map_buffered_bytes", "Descriptor bytes held by open sessions.",
                lambda: self.registry.buffered_bytes)
        m.gauge("sprint_map_component_cache_bytes", "Bytes of components in the shared cache.",
                lambda: self.cache.nbytes)
        m.gauge("sprint_map_frame_batches", "Batched searches of frames so far.",
                lambda: self.batcher.stats.batches if self.batcher else 0)
        m.gauge("sprint_map_frame_batch_size", "Frames in the latest batched search.",
                lambda: self.batcher.stats.last_size if self.batcher else 0)
        #: The garbage collector's pauses (every frame in flight waits for one).
        self.gc_pauses = GcPauses()
        m.histogram_view("sprint_map_gc_pause_seconds", "Garbage collector pauses, by "
                         "generation (frames in flight wait for them).",
                         self.gc_pauses.buckets, self.gc_pauses.series)
        m.gauge("sprint_map_gc_frozen_objects", "Objects frozen out of the garbage collector "
                "once started (serve: the start-up heap).", gc.get_freeze_count)
        m.gauge("sprint_map_map_vertices", "Vertices in the map.",
                lambda: self._stats().get("vertices", 0))
        m.gauge("sprint_map_map_sequences", "Sequences in the map.",
                lambda: self._stats().get("sequences", 0))

    # --- lifecycle --------------------------------------------------------------------------
    async def start(self) -> None:
        """Load the index (so no frame loads it concurrently), start the writer and expiry."""
        self._limiter = anyio.CapacityLimiter(self.config.frame_workers)
        await anyio.to_thread.run_sync(self._warm)
        self.writer.start()
        if self.batcher is not None:
            self.batcher.start()
        self._expiry = asyncio.create_task(self._expire_loop())
        if self.settle_heap:  # after the index load: what start-up made stays frozen
            settle()
        self.gc_pauses.install()  # (after settle's own collection: the pauses of serving)
        self.ready = True

    def _warm(self) -> None:
        # The index loads lazily on the first search; do it now, alone.
        self.map.search(np.zeros((1, self.dim), np.float32), 1)

    async def shutdown(self) -> None:
        """Finish or discard open sessions (``config.on_shutdown``), stop the writer, close."""
        self.ready = False
        self.closing = True
        if self._expiry is not None:
            self._expiry.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._expiry
        pending: list[Future[CommitOutcome]] = []
        for session in self.registry.all():
            if session.state != OPEN:
                continue
            if self.config.on_shutdown == "commit" and session.frames:
                try:
                    pending.append(self.writer.submit(self._job(session)))
                except ApiError:  # the commit queue is full: this one is discarded
                    log.warning("shutdown: commit queue full, session %s discarded", session.id)
            self.registry.remove(session)
            self.metrics.sessions.inc(how="shutdown")
        for future in pending:
            try:
                outcome = await asyncio.wrap_future(future)
            except Exception as exc:  # nothing of it was committed
                log.warning("shutdown: a session's commit failed: %s", exc)
                continue
            self.metrics.commits.inc(result="ok")
            self.metrics.edges.inc(outcome.edges_added)
        await anyio.to_thread.run_sync(self._close)
        self.gc_pauses.uninstall()

    def _close(self) -> None:
        if self.batcher is not None:
            self.batcher.stop()
        self.writer.stop()
        if self.owns_map:
            with self.gate.exclusive():
                self.map.close()  # persists the index

    def _changed(self, component_ids: set[int]) -> None:
        """A commit changed these components (writer thread, gate held exclusively)."""
        self.cache.invalidate(component_ids)
        self.registry.notify_changed(component_ids)

    def _stats(self) -> dict[str, int]:
        if self.map.closed:
            return {}
        with self.gate.shared():
            return self.map.stats()

    # --- sessions ---------------------------------------------------------------------------
    async def create_session(self, name: str | None, lag: int = 0) -> Session:
        """A new session; with ``lag`` (frames) each frame is answered ``lag`` frames late,
        from the fixed-lag smoothed posterior, and the commit answers the last ``lag``."""
        self._refuse_if_closing()
        name = session_name(name)
        try:
            lag = validate_lag(lag)
        except SprintMapError as exc:
            raise ApiError(422, "bad_payload", str(exc)) from None
        if lag and self.localizers is not None:
            raise ApiError(422, "lag_not_supported", "sessions with a lag are not served by "
                           "Ray replicas (serve --ray): start the session without one")
        session = await anyio.to_thread.run_sync(self._new_session, name, lag)
        self.registry.add(session)
        self.metrics.sessions.inc(how="created")
        return session

    def _new_session(self, name: str | None, lag: int = 0) -> Session:
        with self.gate.shared():
            if name is not None:
                try:
                    self.map.sequence_by_name(name)
                except SprintMapError:
                    pass
                else:
                    raise ApiError(409, "duplicate_name",
                                   f"the map already has a sequence named {name!r}")
            k = self.map.config.hmm.k
            if lag:  # searches max(k, smooth_k) deep and records those hits for the commit
                lagged = LaggedLocalizer(self.map, lag, cache=self.cache, record=True)
                return Session(name, lagged.localizer, self.dim, lagged, lagged.depth)
            try:
                localizer = (self.localizers() if self.localizers is not None
                             else Localizer(self.map, cache=self.cache, record=True,
                                            record_k=k))
            except SprintMapError as exc:  # e.g. no replica could take the session
                raise from_library(exc) from None
            return Session(name, localizer, self.dim, search_k=k)

    async def discard(self, session_id: str) -> Session:
        session = self.registry.get(session_id)
        async with session.lock:  # after the frame in progress
            if session.state == COMMITTING:
                raise ApiError(409, "committing", "the session is being committed")
            self.registry.remove(session)
        self.metrics.sessions.inc(how="discarded")
        return session

    async def _expire_loop(self) -> None:
        ttl = self.config.session_ttl_s
        while True:
            await asyncio.sleep(min(max(ttl / 4, 0.05), 5.0))
            for session in self.registry.idle(ttl):
                self.registry.remove(session)
                self.metrics.sessions.inc(how="expired")

    # --- frames -----------------------------------------------------------------------------
    async def frame(self, session_id: str, content_type: str | None, body: bytes
                    ) -> dict[str, Any]:
        """Answer one frame of a session (in the session's order)."""
        self._refuse_if_closing()
        session = self.registry.get(session_id)
        session.touch()
        if session.waiting >= self.config.max_pending_frames:
            self.metrics.rejected.inc(reason="session_pending")
            raise ApiError(429, "too_many_pending", f"{session.waiting} frames of this session "
                           "are already waiting; send the next frame after an answer",
                           {"Retry-After": "1"})
        if self._admitted >= self.config.max_queued_frames:
            self.metrics.rejected.inc(reason="server_queue")
            raise busy(f"{self._admitted} frames are waiting for a worker; retry later")
        kind = media_type(content_type)
        if kind in JSON_TYPES:
            payload = "descriptor"
        elif kind == RAW_TYPE:
            payload = "raw"
        elif kind.startswith("image/"):
            payload = "image"
        else:
            raise ApiError(415, "unsupported_media_type", "send application/json "
                           '{"descriptor": [...]}, application/octet-stream float32 or the '
                           "encoded image with an image/* type")
        start = time.perf_counter()
        session.waiting += 1
        self._admitted += 1
        try:
            async with session.lock:
                if session.state == CLOSED:  # committed or discarded while this one waited
                    raise unknown_session(session_id)
                if session.state != OPEN:
                    raise ApiError(409, "committing", "the session is being committed")
                self.registry.reserve_frame(session)
                try:
                    decision, timing = await self._answer(session, payload, body)
                finally:  # kept or not, the registry counts what the session holds now
                    self.registry.settle(session)
        finally:
            session.waiting -= 1
            self._admitted -= 1
            session.touch()
        elapsed = time.perf_counter() - start
        m = self.metrics
        m.frames.inc(result="waiting" if decision is None
                     else "match" if decision.is_match else "no_match")
        m.frame_seconds.observe(elapsed, payload=payload)
        m.retrieval_seconds.observe(timing[0] / 1e3)
        m.hmm_seconds.observe(timing[1] / 1e3)
        # a lagged session's first frames answer none yet: every field null
        out: dict[str, Any] = decision.to_dict() if decision is not None else dict(_NONE_YET)
        out["timing"] = {"retrieval_ms": round(timing[0], 4), "hmm_ms": round(timing[1], 4),
                         "server_ms": round(elapsed * 1e3, 4)}
        return out

    async def _answer(self, session: Session, payload: str, body: bytes
                      ) -> tuple[Any, tuple[float, float]]:
        """Decode the frame and localise it: batched with other sessions' frames
        (:mod:`.batcher`), or alone in a frame worker when batching is off."""
        assert self._limiter is not None
        if self.batcher is None:
            return await anyio.to_thread.run_sync(self._step, session, payload, body,
                                                  limiter=self._limiter)
        if payload == "raw":  # a few microseconds: no thread hop
            row, position = descriptor_from_raw(body, self.dim), None
        else:  # JSON parsing, image decoding and description: in a worker
            row, position = await anyio.to_thread.run_sync(self._decode, payload, body,
                                                           limiter=self._limiter)
        return await self.batcher.submit(session, row, position)

    def _decode(self, payload: str, body: bytes
                ) -> tuple[np.ndarray, tuple[float, ...] | None]:
        """A frame's body as a validated row, and its position if given."""
        if payload == "descriptor":
            data = parse_json(body)
            return descriptor_from_json(data, self.dim), position_from_json(data)
        if payload == "raw":
            return descriptor_from_raw(body, self.dim), None
        return (descriptor_from_image(body, self.spec, self.dim, self.config.max_image_pixels),
                None)

    def _step(self, session: Session, payload: str, body: bytes
              ) -> tuple[Any, tuple[float, float]]:
        """Worker thread (batching off): body -> row (outside the gate) -> filter step
        (shared gate)."""
        row, position = self._decode(payload, body)
        with self.gate.shared():
            try:
                decision = session.step(row, position)
            except SprintMapError as exc:
                raise from_library(exc) from None
        timing = session.localizer.timing
        return decision, (timing.retrieval_ms[-1], timing.hmm_ms[-1])

    # --- commits ----------------------------------------------------------------------------
    def _job(self, session: Session, pending: list[Any] | None = None) -> CommitJob:
        rows = session.descriptors()
        # the vehicles were answered from k hits; the commit searches the drive smooth_k deep
        return CommitJob(session.name, rows, [*session.decisions, *(pending or ())],
                         source=f"sprint-map serve session {session.id}",
                         positions=session.position_array(),
                         smoothed=functools.partial(self.map.smoothed, session.localizer, rows),
                         centring=session.centring)

    async def commit(self, session_id: str) -> dict[str, Any]:
        """Commit a session's drive; returns once the commit is durable."""
        self._refuse_if_closing()
        session = self.registry.get(session_id)
        session.touch()
        start = time.perf_counter()
        async with session.lock:  # after its frames in progress, in order
            if session.state != OPEN:
                raise ApiError(409, "committing", "the session is already being committed")
            if not session.frames:
                raise ApiError(409, "empty_session", "the session has no frames to commit")
            # A lagged session's last answers, read without changing it: a refused commit
            # (503 below, or a failed write) leaves the drive as it was.
            flushed = (await anyio.to_thread.run_sync(self._pending, session)
                       if session.lagged is not None else None)
            future = self.writer.submit(self._job(session, flushed))
            session.state = COMMITTING
            # Settled in the writer thread, before the awaiting request resumes (and even if
            # the client went away): a durable commit closes the session, a failed one reopens.
            future.add_done_callback(lambda f: self._settle(session, f))
            try:
                outcome = await asyncio.wrap_future(future)
            except SprintMapError as exc:
                raise from_library(exc) from None
        m = self.metrics
        m.commit_seconds.observe(time.perf_counter() - start)
        m.commit_exclusive_seconds.observe(outcome.exclusive_s)
        m.edges.inc(outcome.edges_added)
        added = outcome.added
        out: dict[str, Any] = {
            "seq_id": added.sequence.seq_id if added else None, "name": outcome.name,
            "frames": outcome.frames, "frames_stored": outcome.frames_stored,
            "frames_skipped": outcome.frames - outcome.frames_stored,
            "edges_added": outcome.edges_added, "component": added.component if added else None}
        if flushed is not None:  # the lagged session's last answers, in frame order
            out["decisions"] = [{key: d.to_dict()[key] for key in _ANSWER_FIELDS}
                                for d in flushed]
        return out

    def _pending(self, session: Session) -> list[Any]:
        """A lagged session's last answers, unchanged (worker thread, shared gate)."""
        with self.gate.shared():
            try:
                return session.pending()
            except SprintMapError as exc:
                raise from_library(exc) from None

    def _settle(self, session: Session, future: Future[CommitOutcome]) -> None:
        if future.exception() is None:
            self.registry.remove(session)
            self.metrics.commits.inc(result="ok")
            self.metrics.sessions.inc(how="committed")
        else:
            session.state = OPEN
            self.metrics.commits.inc(result="error")

    async def join(self, source: str, options: dict[str, Any]) -> dict[str, Any]:
        """Join another map's drives into the served map through the writer (in order with
        the commits; sessions keep streaming meanwhile); returns once durable."""
        self._refuse_if_closing()
        future = self.writer.submit(JoinJob(source, options))
        try:
            result = await asyncio.wrap_future(future)
        except SprintMapError as exc:
            raise from_library(exc) from None
        self.metrics.edges.inc(result.cross_edges)
        out: dict[str, Any] = result.to_dict()
        return out

    # --- map --------------------------------------------------------------------------------
    async def map_info(self) -> dict[str, Any]:
        def info() -> dict[str, Any]:
            with self.gate.shared():
                return self.map.info()

        return await anyio.to_thread.run_sync(info)

    def _refuse_if_closing(self) -> None:
        if self.closing:
            raise ApiError(503, "shutting_down", "the server is shutting down")
