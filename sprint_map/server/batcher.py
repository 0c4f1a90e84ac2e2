"""FrameBatcher: the frames of all sessions searched together, then each session's HMM stepped.

One k-NN search of B frames costs far less than B searches of one (the index is read once per
batch, and the matrix product runs at BLAS speed): on the Nordland HoG map, ~0.2-0.5 ms per
frame in a batch of 16-64 against ~1-1.5 ms alone. So frames do not search one by one: the
event loop hands each decoded frame to :meth:`FrameBatcher.submit`, and one thread takes every
frame waiting (up to ``max_frames``), searches them in one call under the map gate's shared
side, and steps each frame's session with its hits
(:meth:`sprint_map.server.sessions.Session.step`), in arrival order. While fewer frames wait
than the larger of the last two batches held, it waits for more, until ``window_s`` after the
oldest one arrived (and at least half a window after the last batch was answered): sessions
that were just answered send their next frames at about the same time, so the batch they made
is expected again, and a fleet that fell into two groups answered in turn (each group's frames
arriving while the other's are stepped) is batched whole again; a lone vehicle's frame
(previous batches: 1) is searched at once, and a batch that took longer than the window finds
the next one ready.

Answers equal offline ``localize`` frame for frame: the map's search gives a query the same
ids and distances, bit for bit, whatever else is in its batch
(:func:`sprint_map.util.exact_search.certified_search`), and the gate keeps commits out
between the search and the steps. A session has at most one frame in a batch (its frames run
one at a time, under its lock), so its frames keep their order.

Answers go back to the event loop in bulk (:class:`Outbox`): once the batch's last session is
stepped, all its answers are handed over with one wake-up of the loop
(``call_soon_threadsafe``, a write to its self-pipe), and the loop resolves them all. Handing
each answer over as its step ended woke the loop once per frame, and the loop (sending answers)
and the batcher (stepping the next session) then traded the GIL at every answer, each trade a
wake-up and a context switch, and a wait of up to the interpreter's switch interval (5 ms) for
the thread that lost it: on Nordland, 16 vehicles, the server's CPU per frame went from
0.89-0.94 ms to 0.64-0.69 ms and the p50 from ~15 to ~11 ms when the answers went in bulk
(``docs/benchmarks.md``, "Service").

Cost per batch: one search of B rows, then B HMM steps (Python, serial: the GIL would
serialise them anyway).
"""

from __future__ import annotations

import asyncio
import collections
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from sprint_map import FrameDecision
from sprint_map.errors import SprintMapError
from sprint_map.map import SprintMap
from sprint_map.server.errors import ApiError, from_library
from sprint_map.server.gate import MapGate
from sprint_map.server.sessions import Session

__all__ = ["BatchStats", "FrameBatcher", "Outbox", "Pending"]

#: A frame's answer: the decision, and its (retrieval ms share, HMM ms).
Answer = tuple[FrameDecision | None, tuple[float, float]]
_NO_IDS = np.empty(0, np.int64)
_NO_DISTS = np.empty(0, np.float32)


@dataclass
class Pending:
    """One frame waiting for its batch; ``future`` belongs to the event loop that sent it."""

    session: Session
    row: np.ndarray
    position: tuple[float, ...] | None
    future: asyncio.Future[Answer]
    arrived: float = field(default_factory=time.perf_counter)


class Outbox:
    """Answers on their way from the batcher thread to the event loops that wait for them.

    :meth:`post_all` (any thread; the batcher posts each batch's answers at once) queues
    answers or errors, and wakes each future's loop only if no wake-up of that loop is pending;
    the woken loop resolves everything queued for it by then (a future already cancelled is
    left alone). Thread-safe.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._ready: dict[asyncio.AbstractEventLoop,
                          list[tuple[asyncio.Future[Answer], Answer | BaseException]]] = {}

    def post(self, future: asyncio.Future[Answer], outcome: Answer | BaseException) -> None:
        """Queue ``outcome`` (an answer, or the exception to raise) for ``future``. O(1)."""
        self.post_all([(future, outcome)])

    def post_all(self, items: list[tuple[asyncio.Future[Answer], Answer | BaseException]]
                 ) -> None:
        """Queue several outcomes with at most one wake-up of each loop. O(len(items))."""
        by_loop: dict[asyncio.AbstractEventLoop,
                      list[tuple[asyncio.Future[Answer], Answer | BaseException]]] = {}
        for item in items:
            by_loop.setdefault(item[0].get_loop(), []).append(item)
        for loop, group in by_loop.items():
            with self._lock:
                waiting = self._ready.get(loop)
                if waiting is not None:  # a wake-up of that loop is pending: it takes these too
                    waiting.extend(group)
                    continue
                self._ready[loop] = group
            try:
                loop.call_soon_threadsafe(self._deliver, loop)
            except RuntimeError:  # the loop is closed: nobody waits for these any more
                with self._lock:
                    self._ready.pop(loop, None)

    def _deliver(self, loop: asyncio.AbstractEventLoop) -> None:
        """In ``loop``: resolve every future queued for it. O(answers)."""
        with self._lock:
            ready = self._ready.pop(loop, [])
        for future, outcome in ready:
            if future.done():  # its request was cancelled
                continue
            if isinstance(outcome, BaseException):
                future.set_exception(outcome)
            else:
                future.set_result(outcome)


@dataclass
class BatchStats:
    """Counts for the metrics: batches searched and frames in them."""

    batches: int = 0
    frames: int = 0
    last_size: int = 0


class FrameBatcher:
    """Batches frames of all sessions into one search (see the module docstring).

    Parameters
    ----------
    smap : SprintMap
        The served map.
    gate : MapGate
        Its readers-writer gate; a batch holds the shared side from search to last step.
    k : int
        Neighbours per frame (the sessions' ``HMMConfig.k``).
    window_s : float
        How long after the oldest waiting frame a batch may wait for more.
    max_frames : int
        Most frames per batch.
    search_threads : int
        OpenMP threads of the search.
    """

    def __init__(self, smap: SprintMap, gate: MapGate, k: int, window_s: float,
                 max_frames: int, search_threads: int = 1) -> None:
        self.map = smap
        self.gate = gate
        self.k = k
        self.window_s = window_s
        self.max_frames = max_frames
        self.search_threads = search_threads
        self.stats = BatchStats()
        self.outbox = Outbox()
        self._queue: collections.deque[Pending] = collections.deque()
        self._cond = threading.Condition()
        self._stopping = False
        self._thread: threading.Thread | None = None
        self._expect = 1  # frames the previous batch held: the next one waits for as many
        self._expect_before = 1  # ... or as many as the one before, if more

    @property
    def alive(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="sprint-map-batcher",
                                        daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Answer what is waiting, then end the thread."""
        with self._cond:
            self._stopping = True
            self._cond.notify()
        if self._thread is not None:
            self._thread.join()

    def submit(self, session: Session, row: np.ndarray,
               position: tuple[float, ...] | None = None) -> asyncio.Future[Answer]:
        """Queue one frame (a validated ``(dim,)`` float32 row); its future gets the answer
        or the error (an :class:`ApiError`). Called in an event loop: the future is of that
        loop."""
        pending = Pending(session, np.asarray(row, dtype=np.float32).reshape(-1), position,
                          asyncio.get_running_loop().create_future())
        with self._cond:
            if self._stopping:
                raise ApiError(503, "shutting_down", "the server is shutting down")
            self._queue.append(pending)
            if len(self._queue) == 1 or len(self._queue) >= min(self._expect, self.max_frames):
                self._cond.notify()
        return pending.future

    def _run(self) -> None:
        self.map.cap_search_threads(self.search_threads)
        while True:
            batch = self._next_batch()
            if batch is None:
                return
            self._answer(batch)

    def _next_batch(self) -> list[Pending] | None:
        free = time.perf_counter()  # when the previous batch was answered
        with self._cond:
            while not self._queue:
                if self._stopping:
                    return None
                self._cond.wait()
            deadline = max(self._queue[0].arrived + self.window_s, free + self.window_s / 2)
            expect = min(max(self._expect, self._expect_before), self.max_frames)
            while (len(self._queue) < expect and not self._stopping
                   and (left := deadline - time.perf_counter()) > 0):
                self._cond.wait(left)
            n = min(len(self._queue), self.max_frames)
            self._expect_before, self._expect = self._expect, n
            return [self._queue.popleft() for _ in range(n)]

    def _answer(self, batch: list[Pending]) -> None:
        """Search the batch in one call, step each session in arrival order, then hand every
        answer to the event loop at once."""
        self.stats.batches += 1
        self.stats.frames += len(batch)
        self.stats.last_size = len(batch)
        outcomes: list[tuple[asyncio.Future[Answer], Answer | BaseException]] = []
        try:
            with self.gate.shared():
                start = time.perf_counter()
                hits = self._search(batch)
                share = (time.perf_counter() - start) * 1e3 / len(batch)
                for pending, (ids, dists) in zip(batch, hits, strict=True):
                    outcomes.append((pending.future, self._step(pending, ids, dists, share)))
        except BaseException as exc:  # the search failed: the frames not stepped get it
            err = from_library(exc) if isinstance(exc, SprintMapError) else exc
            outcomes += [(pending.future, err) for pending in batch[len(outcomes):]]
            if not isinstance(exc, Exception):
                raise
        finally:
            self.outbox.post_all(outcomes)

    def _search(self, batch: list[Pending]) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each frame's ``(ids, distances)``, as deep as its session reads (``search_k``:
        ``k``, or more for a lagged session): one search per depth in the batch."""
        depths = [p.session.search_k or self.k for p in batch]
        out: list[tuple[np.ndarray, np.ndarray]] = [(_NO_IDS, _NO_DISTS)] * len(batch)
        for depth in sorted(set(depths)):
            where = [i for i, d in enumerate(depths) if d == depth]
            dists, ids = self.map.search(  # each frame as its session's map space holds it
                np.stack([batch[i].session.centred(batch[i].row) for i in where]), depth)
            for j, i in enumerate(where):
                out[i] = (ids[j], dists[j])
        return out

    @staticmethod
    def _step(pending: Pending, ids: np.ndarray, dists: np.ndarray, share: float
              ) -> Answer | BaseException:
        """One session's HMM step with its hits: the answer, or the error for its request."""
        try:
            decision = pending.session.step(pending.row, pending.position,
                                            hits=(ids, dists, share))
        except SprintMapError as exc:
            return from_library(exc)
        except Exception as exc:  # noqa: BLE001 - handed to the request, which answers it
            return exc
        timing = pending.session.localizer.timing
        return decision, (share, timing.hmm_ms[-1])
