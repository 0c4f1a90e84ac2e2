"""Localiser replicas: ``sprint-map serve MAP --ray ...`` answers frames in Ray actors.

The HTTP app, the sessions' bookkeeping and the one commit writer stay in the serving process
(the API does not change). Each session's localiser lives in a :class:`ReplicaWorker` actor
(one per replica, spread over the cluster's nodes), which opens the map read-only (a shared
filesystem) and steps that session's filter frame by frame, in the session's order. The serving
process holds a :class:`RemoteLocalizer` per session, the proxy the service uses in place of an
in-process :class:`~sprint_map.localize.localizer.Localizer`: ``step`` is one Ray call, the components a
commit changed travel with the session's next frame (``invalidate``), and the commit's smoothing
runs in the replica (``smoothed``), which reads the map as the writer left it.

A replica that dies takes its sessions with it: their next request is answered 503
``replica_lost`` (:class:`~sprint_map.errors.ReplicaLostError`), the other replicas' sessions go
on, and the pool replaces the dead replica for new sessions.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import threading
import weakref
from typing import Any

import numpy as np

from sprint_map import DriveCentring, FrameDecision, HMMConfig, Localizer, Timing
from sprint_map.errors import ReplicaLostError
from sprint_map.fleet.shards import alive_nodes, spread
from sprint_map.map import SprintMap
from sprint_map.util.arrays import Descriptors

__all__ = ["RemoteLocalizer", "ReplicaPool", "ReplicaWorker"]


class ReplicaWorker:
    """Sessions' localisers over a read-only map (run as a Ray actor by :class:`ReplicaPool`).

    Notes
    -----
    Per frame: what ``Localizer.step`` costs (one k-NN search, one HMM step). Memory: the
    map's index (as a reader holds it) plus each session's filter and recorded hits.
    """

    def __init__(self, path: str, hmm: HMMConfig | None = None) -> None:
        self.map = SprintMap.open(path, readonly=True)
        self.hmm = hmm
        self.sessions: dict[str, Localizer] = {}
        self.map.search(np.zeros((1, self.map.config.dim), np.float32), 1)  # load the index

    def open(self, session: str) -> DriveCentring:
        """Open ``session``; returns its centring, fresh (the prior it is localised with)."""
        localizer = Localizer(self.map, self.hmm, record=True)
        self.sessions[session] = localizer
        return localizer.centring.fresh()

    def step(self, session: str, row: Descriptors, changed: list[int] | None
             ) -> tuple[FrameDecision, float, float]:
        """One frame of ``session``; ``changed``: components commits changed since its last."""
        localizer = self.sessions[session]
        if changed is not None:
            localizer.invalidate(changed)
        decision = localizer.step(row)
        return decision, localizer.timing.retrieval_ms[-1], localizer.timing.hmm_ms[-1]

    def smoothed(self, session: str) -> list[FrameDecision]:
        return self.map.smoothed(self.sessions[session])

    def close(self, session: str) -> None:
        self.sessions.pop(session, None)

    def pid(self) -> int:
        """The process running this replica (tests kill it)."""
        return os.getpid()

    def count(self) -> int:
        return len(self.sessions)


class RemoteLocalizer:
    """The serving process's handle on one session's localiser in a replica.

    Implements what the service uses of a :class:`~sprint_map.localize.localizer.Localizer`: ``step``,
    ``invalidate``, ``smoothed``, ``timing``, ``centring``, ``hits`` (none here). The replica forgets the session when this handle is
    garbage-collected (the session committed, discarded or expired).
    """

    def __init__(self, pool: ReplicaPool, slot: int, actor: Any) -> None:
        self._pool = pool
        self._slot = slot
        self._actor = actor
        self.session = f"s{next(pool.counter)}"
        self.timing = Timing()
        self.record = True
        #: the recorded hits are the replica's (its memory): none are held in this process
        self.hits: list[tuple[np.ndarray, np.ndarray]] = []
        self._changed: set[int] | None = None
        #: the drive's centring as the replica began it (its prior): the commit centres the
        #: posted rows with it, as the replica did frame by frame (``step`` sends them raw)
        self.centring: DriveCentring = self._call(actor.open.remote(self.session))
        weakref.finalize(self, _forget, actor, self.session)

    def _call(self, ref: Any) -> Any:
        ray = self._pool.ray
        try:
            return ray.get(ref)
        except (ray.exceptions.RayActorError, ray.exceptions.ActorUnavailableError) as exc:
            self._pool.lost(self._slot, self._actor)
            raise ReplicaLostError("this session's localiser replica died; its frames are "
                                   "lost: start a new session") from exc

    def invalidate(self, component_ids: Any = None) -> None:
        """Commits changed these components: told to the replica with the next frame."""
        if self._changed is None:
            self._changed = set()
        self._changed.update(int(c) for c in component_ids or ())

    def step(self, row: Descriptors) -> FrameDecision:
        changed = sorted(self._changed) if self._changed is not None else None
        decision: FrameDecision
        decision, retrieval_ms, hmm_ms = self._call(
            self._actor.step.remote(self.session, np.asarray(row, np.float32), changed))
        self._changed = None
        self.timing.retrieval_ms.append(retrieval_ms)
        self.timing.hmm_ms.append(hmm_ms)
        return decision

    def smoothed(self, descriptors: Descriptors | None = None) -> list[FrameDecision]:
        """The session's smoothed decisions, made in its replica (which recorded every
        frame's ``smooth_k`` hits: ``descriptors`` are not needed, so not sent)."""
        decisions: list[FrameDecision] = self._call(self._actor.smoothed.remote(self.session))
        return decisions


def _forget(actor: Any, session: str) -> None:
    with contextlib.suppress(Exception):  # the replica or Ray is gone already: nothing to do
        actor.close.remote(session)


class ReplicaPool:
    """``replicas`` :class:`ReplicaWorker` actors over the map at ``path``, spread over the
    cluster's nodes; new sessions go round robin to the live ones.

    Notes
    -----
    Starting: one actor per replica, each opening the map and loading its index (in parallel).
    """

    def __init__(self, path: str, replicas: int = 2, *, hmm: HMMConfig | None = None,
                 actor_options: dict[str, Any] | None = None) -> None:
        from sprint_map.fleet.runtime import require_ray

        if replicas < 1:
            raise ValueError("replicas must be >= 1")
        self.ray = require_ray()
        self.path = path
        self.hmm = hmm
        self._remote = self.ray.remote(ReplicaWorker)
        self._options = actor_options or {}
        self._nodes = alive_nodes(self.ray)
        self.counter = itertools.count()
        self._lock = threading.Lock()
        self._next = itertools.count()
        self.replaced = 0
        self.actors = [self._start(n) for n in range(replicas)]
        self.ray.get([a.count.remote() for a in self.actors])  # every replica is up

    def _start(self, slot: int) -> Any:
        options = {"num_cpus": 0, "max_restarts": 0,
                   "scheduling_strategy": spread(self._nodes, slot), **self._options}
        return self._remote.options(**options).remote(self.path, self.hmm)

    def localizer(self) -> RemoteLocalizer:
        """A new session's localiser, on the next replica (round robin); a dead replica met
        on the way is replaced and the next one tried.

        Raises
        ------
        ReplicaLostError
            Every replica tried died.
        """
        for attempt in itertools.count():
            with self._lock:
                slot = next(self._next) % len(self.actors)
                actor = self.actors[slot]
            try:
                return RemoteLocalizer(self, slot, actor)
            except ReplicaLostError:
                if attempt >= len(self.actors):
                    raise
        raise AssertionError("unreachable")

    def lost(self, slot: int, actor: Any) -> None:
        """Replica ``actor`` of ``slot`` died: new sessions go to a fresh one."""
        with self._lock:
            if self.actors[slot] is actor:
                self._nodes = alive_nodes(self.ray)
                self.actors[slot] = self._start(slot)
                self.replaced += 1

    def pids(self) -> list[int]:
        return [int(p) for p in self.ray.get([a.pid.remote() for a in self.actors])]

    def close(self) -> None:
        for actor in self.actors:
            self.ray.kill(actor)
        self.actors = []
