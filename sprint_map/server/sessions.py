"""Sessions: one per drive, each with its own filter state, and the registry that bounds them.

A session is a vehicle's drive in progress: its :class:`~sprint_map.localize.localizer.Localizer` (the
SPRINT filter's belief), the descriptors it streamed and the decisions it was answered, kept
until the drive is committed (as ``ingest`` would commit it) or discarded. Frames of a session
run one at a time, in arrival order (``lock``, FIFO); sessions run concurrently.

Lifecycle: ``open`` -> (``committing`` -> ``closed`` | back to ``open`` if the commit failed)
or -> ``closed`` (discarded, expired, shut down).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import threading
import time
import uuid
from collections.abc import Callable, Container, Iterable
from typing import TYPE_CHECKING

import numpy as np

from sprint_map import DriveWriter, FrameDecision, LaggedLocalizer, Localizer
from sprint_map.server.errors import ApiError, busy, unknown_session
from sprint_map.util.arrays import Descriptors

if TYPE_CHECKING:
    from sprint_map import DriveCentring

__all__ = ["CLAIMED_NAMES", "CLOSED", "COMMITTING", "OPEN", "Session", "SessionRegistry"]

OPEN, COMMITTING, CLOSED = "open", "committing", "closed"

#: How many default names of recent unnamed commits stay claimed (see ``begin_default``).
CLAIMED_NAMES = 64


class Session:
    """One drive in progress. Mutated only by its own frame (under ``lock``) and the writer.

    ``changed`` is written by the commit writer while it holds the map gate exclusively and read
    by this session's next frame under the shared gate: the gate orders the two.
    """

    def __init__(self, name: str | None, localizer: Localizer, dim: int,
                 lagged: LaggedLocalizer | None = None, search_k: int = 0) -> None:
        self.id = uuid.uuid4().hex
        self.name = name
        #: The localizer recording the drive (the commit smooths it): ``lagged.localizer`` for
        #: a lagged session.
        self.localizer = lagged.localizer if lagged is not None else localizer
        #: A session created with a lag answers frame ``t - lag`` when frame ``t`` is posted.
        self.lagged = lagged
        self.lag = lagged.lag if lagged is not None else 0
        #: Neighbours a batched search gives this session's frames.
        self.search_k = search_k
        self.dim = dim
        #: Bytes of the hits recorded for the commit (one entry per frame).
        self.hit_bytes = 0
        #: Bytes the registry counts for this session (:meth:`SessionRegistry.settle`).
        self.counted = 0
        self.rows: list[Descriptors] = []
        #: Per-frame ``(x, y[, heading])``: given for every frame of a session or for none.
        self.positions: list[tuple[float, ...]] = []
        self.decisions: list[FrameDecision] = []
        self.state = OPEN
        self.lock = asyncio.Lock()
        self.waiting = 0  # frame requests admitted for this session (queued or running)
        self.created = time.time()
        self.last_active = time.monotonic()
        #: Components changed by commits since this session's last frame (None: no change).
        self.changed: set[int] | None = None

    @property
    def frames(self) -> int:
        """Frames posted (and kept) so far."""
        return len(self.rows)

    @property
    def nbytes(self) -> int:
        """Bytes this session holds: its descriptors, the hits recorded for its commit and,
        with a lag, the beliefs of the frames waiting for an answer
        (:attr:`FixedLagSmoother.held_bytes <sprint_map.hmm.fixed_lag.FixedLagSmoother.
        held_bytes>`). O(1)."""
        smoother = self.lagged.smoother if self.lagged is not None else None
        return (self.frames * self.dim * 4 + self.hit_bytes
                + (smoother.held_bytes if smoother is not None else 0))

    @property
    def frame_cost(self) -> int:
        """What one more frame is expected to add to :attr:`nbytes`: its descriptor and, once
        a frame was kept, the mean of what the others added beyond theirs (a lagged session's
        waiting beliefs grow until ``lag`` frames wait). O(1)."""
        row = self.dim * 4
        if not self.frames:
            return row
        return max(row, -(-self.nbytes // self.frames))

    def touch(self) -> None:
        self.last_active = time.monotonic()

    def notify_changed(self, component_ids: Iterable[int]) -> None:
        """Record that a commit changed these components (called under the exclusive gate)."""
        if self.changed is None:
            self.changed = set()
        self.changed.update(int(c) for c in component_ids)

    def apply_changes(self) -> None:
        """Tell the filter about commits since the last frame (called under the shared gate)."""
        if self.changed is not None:
            changed, self.changed = self.changed, None
            (self.lagged or self.localizer).invalidate(changed)

    def check_position(self, position: tuple[float, ...] | None) -> None:
        """Refuse a frame that breaks "positions for every frame or for none"."""
        if self.frames and (position is not None) != bool(self.positions):
            given = "gave" if self.positions else "did not give"
            raise ApiError(422, "bad_payload", f"the session's earlier frames {given} a "
                           "position: give one for every frame or for none")

    @property
    def centring(self) -> DriveCentring:
        """The drive's centring (the localizer's, :mod:`sprint_map.frontend.centring`): each
        frame is searched centred on the frames kept before it; the rows kept are as posted
        (the commit's writer centres them again, with the same prior, to the very same rows)."""
        return self.localizer.centring

    def centred(self, row: Descriptors) -> Descriptors:
        """The session's next frame ``row`` as the map searches it (nothing changes)."""
        centred: Descriptors = self.localizer.centred(row)[0]
        return centred

    def step(self, row: Descriptors, position: tuple[float, ...] | None = None,
             hits: tuple[np.ndarray, np.ndarray, float] | None = None
             ) -> FrameDecision | None:
        """Localise one frame and keep it for the commit (called under the shared gate).

        ``hits`` are the frame's ``(ids, distances, retrieval_ms)`` when the caller searched
        it (in a batch with other sessions' frames, :attr:`search_k` deep); otherwise it is
        searched here. A lagged session returns the answer of frame ``frames - 1 - lag``
        (None while fewer frames were posted).
        """
        self.check_position(position)
        self.apply_changes()
        stepper: Localizer | LaggedLocalizer = self.lagged or self.localizer
        recorded = len(self.localizer.hits)
        decision = stepper.step(row) if hits is None else stepper.step_hits(*hits, row)
        for ids, dists in self.localizer.hits[recorded:]:
            self.hit_bytes += ids.nbytes + dists.nbytes + 2 * 112
        self.rows.append(row.reshape(-1))
        if position is not None:
            self.positions.append(position)
        if decision is not None:
            self.decisions.append(decision)
        return decision

    def pending(self) -> list[FrameDecision]:
        """A lagged session's answers of its last frames, as a commit gives them (called under
        the shared gate); nothing changes: a refused commit leaves the session as it was, and
        the next frames and the retried commit answer as ``localize --lag`` would."""
        return self.lagged.pending() if self.lagged is not None else []

    def position_array(self) -> np.ndarray | None:
        """``(frames, 3)`` x, y, heading (NaN if not given), or None without positions."""
        if not self.positions:
            return None
        out = np.full((len(self.positions), 3), np.nan)
        for i, pos in enumerate(self.positions):
            out[i, : len(pos)] = pos
        return out

    def descriptors(self) -> Descriptors:
        """The drive's descriptors, ``(frames, dim)`` float32."""
        return np.stack(self.rows) if self.rows else np.empty((0, self.dim), np.float32)

    def to_dict(self) -> dict[str, object]:
        return {"session_id": self.id, "name": self.name, "frames": self.frames,
                "lag": self.lag, "state": self.state, "created": self.created,
                "idle_s": round(time.monotonic() - self.last_active, 3)}


class SessionRegistry:
    """The open sessions, with the limits on their number and on the bytes they hold.

    Thread-safe: the event loop adds and removes sessions, the writer thread walks them.
    """

    def __init__(self, max_sessions: int, max_frames: int, max_buffered_bytes: int) -> None:
        self.max_sessions = max_sessions
        self.max_frames = max_frames
        self.max_buffered_bytes = max_buffered_bytes
        self._sessions: dict[str, Session] = {}
        self._lock = threading.Lock()
        self._buffered = 0
        #: Default names of the latest unnamed commits (in progress or just done: the map may
        #: not show them to a session being created yet); see :meth:`begin_default`.
        self._claimed: collections.deque[str] = collections.deque(maxlen=CLAIMED_NAMES)

    def __len__(self) -> int:
        return len(self._sessions)

    @property
    def buffered_bytes(self) -> int:
        """Bytes held by all open sessions (:attr:`Session.nbytes`, as last settled, and the
        frames admitted since)."""
        return self._buffered

    def add(self, session: Session) -> None:
        with self._lock:
            if len(self._sessions) >= self.max_sessions:
                raise busy(f"too many open sessions ({self.max_sessions}); commit or discard "
                           "some, or retry later")
            if session.name is not None and any(
                    s.name == session.name for s in self._sessions.values()):
                raise ApiError(409, "duplicate_name",
                               f"an open session is already named {session.name!r}")
            if session.name in self._claimed:
                raise ApiError(409, "duplicate_name", f"an unnamed drive committed as "
                               f"{session.name!r} (its default name) just now")
            self._sessions[session.id] = session

    def begin_default(self, begin: Callable[[Container[str]], DriveWriter]
                      ) -> DriveWriter:
        """Begin an unnamed drive's sequence, its default name avoiding every session's name.

        ``begin(taken)`` chooses the name (:func:`~sprint_map.storage.sequence_writer.
        default_name`) under the registry's lock, and the name is claimed with it: until its
        commit ends (and a while after, when the map holds it), :meth:`add` refuses a session of
        that name, so a session is never promised a name an unnamed drive then takes.
        """
        with self._lock:
            taken = {s.name for s in self._sessions.values() if s.name is not None}
            writer = begin(taken | set(self._claimed))
            self._claimed.append(writer.name)
            return writer

    def release(self, name: str) -> None:
        """Give up the claim of a default name whose commit failed (nothing holds it)."""
        with self._lock, contextlib.suppress(ValueError):
            self._claimed.remove(name)

    def get(self, session_id: str) -> Session:
        session = self._sessions.get(session_id)
        if session is None or session.state == CLOSED:
            raise unknown_session(session_id)
        return session

    def all(self) -> list[Session]:
        with self._lock:
            return list(self._sessions.values())

    def reserve_frame(self, session: Session) -> None:
        """Admit one more frame of ``session`` against the frame and memory limits."""
        if session.frames >= self.max_frames:
            raise ApiError(409, "frame_limit", f"session has reached its limit of "
                           f"{self.max_frames} frames; commit it or discard it")
        cost = session.frame_cost
        with self._lock:
            if self._buffered + cost > self.max_buffered_bytes:
                raise busy(f"the server holds {self._buffered} bytes of uncommitted frames "
                           f"and their state (limit {self.max_buffered_bytes}); retry later")
            self._buffered += cost
            session.counted += cost

    def settle(self, session: Session) -> None:
        """Count what ``session`` holds now (after a frame, kept or not): the estimate
        :meth:`reserve_frame` admitted is replaced by :attr:`Session.nbytes`."""
        with self._lock:
            if session.id in self._sessions:
                held = session.nbytes
                self._buffered += held - session.counted
                session.counted = held

    def remove(self, session: Session) -> None:
        """Close ``session`` and free what it held (idempotent)."""
        with self._lock:
            if self._sessions.pop(session.id, None) is not None:
                self._buffered -= session.counted
                session.counted = 0
            session.state = CLOSED

    def notify_changed(self, component_ids: set[int]) -> None:
        """Tell every open session that a commit changed ``component_ids``."""
        for session in self.all():
            session.notify_changed(component_ids)

    def idle(self, ttl_s: float) -> list[Session]:
        """Open sessions quiet for ``ttl_s`` with nothing in progress (to expire)."""
        now = time.monotonic()
        return [s for s in self.all()
                if s.state == OPEN and not s.waiting and not s.lock.locked()
                and now - s.last_active > ttl_s]
