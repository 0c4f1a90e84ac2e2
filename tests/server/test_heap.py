"""The server's heap (server/heap.py) and the batcher's answers in bulk (server/batcher.py Outbox).

A served process freezes its start-up heap out of the garbage collector's later collections and
reports the collector's pauses; a process that only creates services (this one) does not freeze.
The batcher hands its answers to the event loop with one wake-up for all answers ready, not one
per frame, and every future still gets its own answer.
"""

from __future__ import annotations

import asyncio
import gc
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import pytest

from sprint_map.server.batcher import Outbox
from sprint_map.server.heap import GcPauses
from sprint_map.server.metrics import Metrics


def test_gc_pauses_are_counted_by_generation_until_uninstalled():
    pauses = GcPauses()
    pauses.install()
    pauses.install()  # idempotent: one callback
    try:
        gc.collect(0)
        gc.collect(2)
        gc.collect(2)
    finally:
        pauses.uninstall()
    assert pauses.count(2) >= 2 and pauses.count(0) >= 1
    twice = pauses.count(2)
    gc.collect(2)
    assert pauses.count(2) == twice  # no longer timed
    pauses.uninstall()  # idempotent
    series = pauses.series()
    assert set(series) == {(("generation", g),) for g in ("0", "1", "2")}
    full = series[(("generation", "2"),)]
    assert len(full) == len(pauses.buckets) + 2 and full[-1] > 0  # counts..., sum of pauses


def test_gc_pauses_render_as_a_prometheus_histogram():
    pauses = GcPauses()
    pauses.install()
    try:
        gc.collect(2)
    finally:
        pauses.uninstall()
    metrics = Metrics()
    metrics.histogram_view("sprint_map_gc_pause_seconds", "Pauses.", pauses.buckets,
                           pauses.series)
    lines = metrics.render().splitlines()
    assert "# TYPE sprint_map_gc_pause_seconds histogram" in lines
    full = [float(line.split()[-1]) for line in lines
            if line.startswith('sprint_map_gc_pause_seconds_bucket{generation="2"')]
    assert full == sorted(full) and full[-1] == pauses.count(2)
    assert f'sprint_map_gc_pause_seconds_count{{generation="2"}} {pauses.count(2)}' in lines


SETTLE = """
import gc
from sprint_map.server.heap import settle
before = len(gc.get_objects())
frozen = settle()
assert frozen >= before // 2, (frozen, before)
assert gc.get_freeze_count() == frozen
assert len(gc.get_objects()) < before // 10  # later collections skip the frozen objects

class Node:
    pass

for _ in range(100):  # cycles made after settling are still collected
    a, b = Node(), Node()
    a.other, b.other = b, a
del a, b
assert gc.collect() >= 200
print("ok")
"""


def test_settle_freezes_the_start_up_heap_and_later_cycles_are_still_collected():
    # In a child process: freezing this test process's heap would outlive the test.
    out = subprocess.run([sys.executable, "-c", SETTLE], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


def _metric(text: str, name: str) -> float:
    return float(next(line.split()[-1] for line in text.splitlines()
                      if line.startswith(name + " ")))


def test_a_served_map_freezes_its_heap_and_reports_gc_pauses(one_drive_map: Path,
                                                           start_server: Any):
    server = start_server(one_drive_map)
    text = server.client.get("/metrics").text
    assert _metric(text, "sprint_map_gc_frozen_objects") > 10_000  # FastAPI, NumPy, FAISS...
    assert "# TYPE sprint_map_gc_pause_seconds histogram" in text
    assert 'sprint_map_gc_pause_seconds_count{generation="0"}' in text
    assert server.terminate() == 0


def _count_wakeups(loop: asyncio.AbstractEventLoop) -> list[int]:
    """Count the loop's ``call_soon_threadsafe`` calls (wake-ups from other threads) from now
    on, in the returned one-item list."""
    count = [0]
    wake = loop.call_soon_threadsafe

    def counting(*args: Any, **kwargs: Any) -> Any:
        count[0] += 1
        return wake(*args, **kwargs)

    loop.call_soon_threadsafe = counting  # type: ignore[method-assign]
    return count


async def _bulk(outcomes: list[Any], cancel: int | None) -> tuple[list[Any], int]:
    loop = asyncio.get_running_loop()
    wakeups = _count_wakeups(loop)
    outbox = Outbox()
    futures = [loop.create_future() for _ in outcomes]
    if cancel is not None:
        futures[cancel].cancel()
    # The batcher thread posts every answer while the loop is busy (blocked in join here):
    # one wake-up of the loop is scheduled, and it resolves them all.
    poster = threading.Thread(target=lambda: [outbox.post(f, o)
                                              for f, o in zip(futures, outcomes, strict=True)])
    poster.start()
    poster.join()
    got = await asyncio.gather(*futures, return_exceptions=True)
    # Posts after that delivery wake the loop again.
    late = loop.create_future()
    threading.Thread(target=outbox.post, args=(late, "late")).start()
    got.append(await late)
    return got, wakeups[0]


@pytest.mark.parametrize("cancel", [None, 3])
def test_outbox_answers_each_future_with_one_wakeup_for_all_ready(cancel):
    error = ValueError("frame 5 failed")
    outcomes: list[Any] = [("answer", i) for i in range(12)]
    outcomes[5] = error
    got, wakeups = asyncio.run(_bulk(outcomes, cancel))
    expected: list[Any] = list(outcomes) + ["late"]
    if cancel is not None:
        assert isinstance(got[cancel], asyncio.CancelledError)  # left alone, no error raised
        got[cancel] = expected[cancel]
    assert got == expected
    assert wakeups == 2  # the 12 answers, then the late one


async def _posted_together(n: int) -> tuple[list[Any], int]:
    loop = asyncio.get_running_loop()
    wakeups = _count_wakeups(loop)
    futures = [loop.create_future() for _ in range(n)]
    # As the batcher posts a batch: from its thread, every answer in one call.
    threading.Thread(target=Outbox().post_all,
                     args=([(f, i) for i, f in enumerate(futures)],)).start()
    return await asyncio.gather(*futures), wakeups[0]


def test_a_batch_posted_together_wakes_the_loop_once():
    got, wakeups = asyncio.run(_posted_together(16))
    assert got == list(range(16)) and wakeups == 1


def test_outbox_posting_to_a_closed_loop_is_dropped():
    loop = asyncio.new_event_loop()
    future = loop.create_future()
    loop.close()
    outbox = Outbox()
    outbox.post(future, "nobody waits")  # no error, and the next post tries again
    outbox.post(future, "still nobody")
    assert not future.done()
