"""An ordered, bounded, streaming parallel map over threads or processes.

Image ingest is decode-bound (a 640x480 JPEG takes ~2 ms to decode, its HoG ~0.45 ms), and
OpenCV releases the GIL inside ``imdecode``, ``resize`` and ``HOGDescriptor.compute``, so plain
threads scale over the cores without the start-up and pickling cost of processes (measured by
``tools/bench_frontend.py ingest``). Processes remain available for descriptor code that holds
the GIL.

The map is *streaming*: items are pulled from the input iterator only when a slot frees up, and at
most ``max_in_flight`` tasks are queued or running, so memory stays bounded however long the
input is (a 100k-frame video is never held in RAM).
"""

from __future__ import annotations

import multiprocessing
import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING, TypeVar

if TYPE_CHECKING:
    from concurrent.futures import Executor, Future

__all__ = ["EXECUTORS", "default_workers", "ordered_map"]

T = TypeVar("T")
R = TypeVar("R")

EXECUTORS = ("thread", "process")


def default_workers() -> int:
    """Cores this process may run on (``sched_getaffinity`` honours taskset/cgroup pinning)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def ordered_map(
    fn: Callable[[T], R],
    items: Iterable[T],
    workers: int = 1,
    executor: str = "thread",
    max_in_flight: int | None = None,
    initializer: Callable[[], None] | None = None,
) -> Iterator[R]:
    """Yield ``fn(item)`` for each item, in input order, computed by ``workers`` workers.

    - ``fn``: applied to each item; with ``executor="process"`` it and the items must be
      picklable (a module-level function or a ``functools.partial`` of one).
    - ``items``: consumed lazily, in the calling thread, only as fast as results are consumed.
    - ``workers``: ``1`` runs everything inline in the calling thread (no pool, no overhead).
    - ``executor``: ``"thread"`` or ``"process"`` (started with ``spawn``: forking a process
      whose OpenCV or OpenMP thread pools run can deadlock the child).
    - ``max_in_flight``: tasks submitted, not yet consumed; default ``2 * workers`` (one
      running, one queued per worker, so no worker idles while the consumer handles a result).
    - ``initializer``: run once in each worker process (processes only; picklable).

    Raises whatever ``fn`` raised, for the first failing item in input order; the remaining
    tasks are cancelled and the pool shut down (also when the consumer stops early).
    """
    if workers < 1:
        raise ValueError("workers must be >= 1")
    if executor not in EXECUTORS:
        raise ValueError(f"executor must be one of {', '.join(EXECUTORS)}")
    if workers == 1:
        for item in items:
            yield fn(item)
        return
    limit = max_in_flight if max_in_flight is not None else 2 * workers
    if limit < 1:
        raise ValueError("max_in_flight must be >= 1")
    from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor

    pool: Executor
    if executor == "thread":
        pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="sprint-frontend")
    else:
        pool = ProcessPoolExecutor(
            max_workers=workers,
            mp_context=multiprocessing.get_context("spawn"),
            initializer=initializer,
        )
    pending: deque[Future[R]] = deque()
    source = iter(items)
    exhausted = False
    try:
        while True:
            while not exhausted and len(pending) < limit:
                try:
                    item = next(source)
                except StopIteration:
                    exhausted = True
                    break
                pending.append(pool.submit(fn, item))
            if not pending:
                return
            yield pending.popleft().result()
    finally:
        for future in pending:
            future.cancel()
        pool.shutdown(wait=True, cancel_futures=True)
