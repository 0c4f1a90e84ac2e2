"""The ingest farm: drives described and localised as Ray tasks, committed in order by one writer.

``sprint-map ingest MAP A B C ... --ray ...`` hands each drive to a Ray task that opens the map
read-only (a shared filesystem: ``docs/fleet.md``, "Where the map files live"), decodes and
describes the drive's images (or reads its ``.npy``) and localises it against one snapshot of
the map (:meth:`MapService.prepare_ingest <sprint_map.facade.service.MapService.prepare_ingest>`).
The caller is the single writer: it takes the drives back in the given order and commits each
(:meth:`MapService.commit_prepared <sprint_map.facade.service.MapService.commit_prepared>`),
localising again in the writer any drive whose snapshot is stale for what it touched; so the
map that results equals serial ingest in the same order, the same sequences and the same edges.

Faults: a task whose worker dies is retried by Ray (``max_retries``) and only the writer
commits, once per drive, in order: a killed worker loses and duplicates no drive. A writer
killed mid-commit leaves the map as the store's commit protocol does (each drive whole or
absent); running the same command again reports the drives already in as ``already_committed``
(same name and descriptors) and adds the rest.

At most ``window`` drives are in flight (described, localised, not yet committed), which bounds
the writer's memory to ``window`` drives' descriptors.
"""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from sprint_map import HMMConfig, IngestResult, PreparedDrive
from sprint_map.errors import SprintMapError
from sprint_map.map import SprintMap
from sprint_map.util.arrays import Descriptors

__all__ = ["FarmResult", "LocalisedDrive", "farm_ingest", "localise_drive"]

#: Ray retries of a drive's task whose worker died (the task itself is pure: safe to rerun).
TASK_RETRIES = 3


@dataclass(frozen=True)
class LocalisedDrive:
    """What a farm task returns: the drive's search batches, its name, its localisation."""

    source: str
    name: str
    batches: list[Descriptors]
    prepared: PreparedDrive
    worker_pid: int


@dataclass(frozen=True)
class FarmResult:
    """One committed drive: the ingest result, and why it was localised again (None: the
    farm's decisions were committed)."""

    source: str
    result: IngestResult
    relocalised: str | None


def localise_drive(map_path: str, source: str, stride: int = 1, merge: bool = True,
                   hmm: HMMConfig | None = None) -> LocalisedDrive:
    """Describe drive ``source`` and localise it against a snapshot of the map (a Ray task).

    Notes
    -----
    Describing (~2.5 ms per 640x480 image with HoG; a ``.npy`` is read) plus the localisation
    of ``ingest`` (one k-NN search and one HMM step per frame, and the smoothing).
    """
    with SprintMap.open(map_path, readonly=True) as smap:
        src = smap.open_source(source, stride=stride)
        batches = [np.array(b, dtype=np.float32) for b in src.iter_batches()]
        prepared = smap.service.prepare_ingest(batches, merge=merge, hmm=hmm)
        return LocalisedDrive(source, src.name, batches, prepared, os.getpid())


def farm_ingest(smap: SprintMap, sources: Sequence[str], *, names: Sequence[str | None] = (),
                stride: int = 1, merge: bool = True, hmm: HMMConfig | None = None,
                window: int | None = None, task_options: dict[str, Any] | None = None,
                on_commit: Callable[[FarmResult], None] | None = None) -> list[FarmResult]:
    """Ingest ``sources`` into ``smap`` (open for writing) on the Ray runtime this process is
    connected to (:func:`sprint_map.fleet.runtime.connect`), in the given order.

    Parameters
    ----------
    names : sequence of str or None
        Sequence names by position (default, or None: the source's name).
    window : int, optional
        Drives in flight at once (default: twice the cluster's CPUs, at least 2).
    on_commit : callable, optional
        Called with each drive's :class:`FarmResult` as soon as it is committed.

    Returns
    -------
    list of FarmResult, in the order of ``sources``.

    Raises
    ------
    SprintMapError
        What serial ingest would raise for a bad source (the drives before it are committed).
    """
    from sprint_map.fleet.runtime import require_ray

    ray = require_ray()
    task = ray.remote(localise_drive).options(
        max_retries=TASK_RETRIES, retry_exceptions=False, **(task_options or {}))
    if window is None:
        window = max(2, 2 * int(ray.cluster_resources().get("CPU", 1)))
    path = str(smap.path)
    todo: Iterator[tuple[int, str]] = iter(enumerate(sources))
    flight: deque[tuple[int, str, Any]] = deque()

    def submit() -> None:
        for i, source in todo:
            flight.append((i, source, task.remote(path, str(source), stride, merge, hmm)))
            if len(flight) >= window:
                return

    out = []
    submit()
    while flight:
        i, source, ref = flight.popleft()
        drive = _get(ray, ref)
        submit()  # keep the window full while this drive commits
        name = names[i] if i < len(names) and names[i] is not None else drive.name
        result, why = smap.service.commit_prepared(drive.prepared, drive.batches, name, hmm=hmm,
                                           source=str(source))
        done = FarmResult(str(source), result, why)
        out.append(done)
        if on_commit is not None:
            on_commit(done)
    return out


def _get(ray: Any, ref: Any) -> LocalisedDrive:
    """The task's result; the library's own error (a bad source) raised as itself."""
    try:
        result: LocalisedDrive = ray.get(ref)
        return result
    except ray.exceptions.RayTaskError as exc:
        cause = getattr(exc, "cause", None)
        if isinstance(cause, SprintMapError):
            raise cause from None
        raise
