"""Frames of many sessions searched together (server/batcher.py), in process.

Concurrent sessions streaming at once are answered from batched searches, and every answer
equals the offline ``localize`` of the same frames, field for field; with batching off
(``batch_max_frames`` 0) the same. The frame fast path (server/fastpath.py) answers what the
FastAPI route documents.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from sprint_map.map import SprintMap
from sprint_map.server.config import ServerConfig
from sprint_map.server.service import LocalisationService
from tests.helpers.serve import run_service
from tests.helpers.worlds import drive

SESSIONS = 6


async def stream_raw(client: httpx.AsyncClient, rows: np.ndarray) -> list[dict[str, Any]]:
    sid = (await client.post("/v1/sessions")).json()["session_id"]
    out = []
    for row in rows:
        response = await client.post(f"/v1/sessions/{sid}/frames",
                                     content=row.astype("<f4").tobytes(),
                                     headers={"content-type": "application/octet-stream"})
        assert response.status_code == 200, response.text
        out.append(response.json())
    return out


@pytest.mark.parametrize("max_frames", [64, 0])
def test_concurrent_sessions_get_the_offline_answers(one_drive_map: Path, places, rng,
                                                     max_frames):
    drives = [drive(places, rng) for _ in range(SESSIONS)]

    async def body(service: LocalisationService, client: httpx.AsyncClient) -> Any:
        answers = await asyncio.gather(*(stream_raw(client, d) for d in drives))
        stats = service.batcher.stats if service.batcher else None
        return answers, stats

    answers, stats = run_service(one_drive_map, body, batch_max_frames=max_frames,
                                 batch_window_ms=5.0)
    with SprintMap.open(one_drive_map, readonly=True) as m:
        for rows, got in zip(drives, answers, strict=True):
            found, _ = m.localize(rows)
            assert [{k: a[k] for k in ("frame", "seq_id", "image_id", "prob")} for a in got] \
                == [{k: d.to_dict()[k] for k in ("frame", "seq_id", "image_id", "prob")}
                    for d in found]
            assert set(got[0]) == {"frame", "seq_id", "image_id", "prob", "timing"}
    if max_frames:
        assert stats.frames == SESSIONS * len(drives[0])
        assert stats.batches < stats.frames  # frames of several sessions shared searches
    else:
        assert stats is None


def test_fast_path_answers_errors_like_the_api(one_drive_map: Path):
    async def body(service: LocalisationService, client: httpx.AsyncClient) -> Any:
        sid = (await client.post("/v1/sessions")).json()["session_id"]
        path = f"/v1/sessions/{sid}/frames"
        unknown = await client.post("/v1/sessions/nope/frames", content=b"\0" * 8,
                                    headers={"content-type": "application/octet-stream"})
        short = await client.post(path, content=b"\0" * 8,
                                  headers={"content-type": "application/octet-stream"})
        kind = await client.post(path, content=b"x", headers={"content-type": "text/plain"})
        wrong_method = await client.put(path, content=b"")
        metrics = (await client.get("/metrics")).text
        return unknown, short, kind, wrong_method, metrics

    unknown, short, kind, wrong_method, metrics = run_service(one_drive_map, body)
    assert unknown.status_code == 404 and unknown.json()["error"] == "unknown_session"
    assert short.status_code == 422 and short.json()["error"] == "descriptor_shape"
    assert kind.status_code == 415 and kind.json()["error"] == "unsupported_media_type"
    assert wrong_method.status_code == 405  # FastAPI still answers every other request
    assert ('sprint_map_http_requests_total{method="POST",route="/v1/sessions/{session_id}/'
            'frames",status="422"} 1') in metrics


@pytest.mark.parametrize(("field", "value"), [("batch_window_ms", -1.0),
                                              ("batch_max_frames", -1),
                                              ("batch_max_frames", 2.5),
                                              ("search_threads", 0)])
def test_batch_settings_are_checked(field, value):
    with pytest.raises(ValueError, match=field):
        ServerConfig(**{field: value})


def test_a_failed_search_answers_every_frame_of_its_batch(one_drive_map: Path, places, rng,
                                                          monkeypatch):
    from sprint_map.errors import StorageIOError
    from sprint_map.server.batcher import FrameBatcher
    from sprint_map.server.gate import MapGate
    from sprint_map.server.sessions import Session

    rows = drive(places, rng)[:5]

    def broken(queries: np.ndarray, k: int) -> Any:
        raise StorageIOError("the index is unreadable")

    async def body(smap: SprintMap) -> list[Any]:
        batcher = FrameBatcher(smap, MapGate(), k=5, window_s=0.0, max_frames=64)
        sessions = [Session(None, smap.localizer(), smap.config.dim) for _ in rows]
        # Queued before the thread starts: the five frames make one batch.
        futures = [batcher.submit(s, r) for s, r in zip(sessions, rows, strict=True)]
        batcher.start()
        try:
            return await asyncio.gather(*futures, return_exceptions=True)
        finally:
            batcher.stop()

    with SprintMap.open(one_drive_map) as smap:
        monkeypatch.setattr(smap, "search", broken)
        got = asyncio.run(body(smap))
    # Each request gets the library error's answer (503 storage_error), none is left waiting.
    assert [(e.status, e.code, e.message) for e in got] == \
        [(503, "storage_error", "the index is unreadable")] * len(rows)


def test_a_fleet_split_in_two_groups_is_batched_whole_again(one_drive_map: Path, places, rng):
    """Vehicles answered in two alternating groups make whole batches again: a batch waits
    (at most ``window_s``) for as many frames as the larger of the last two batches held."""
    from sprint_map.server.batcher import FrameBatcher
    from sprint_map.server.gate import MapGate
    from sprint_map.server.sessions import Session

    rows = drive(places, rng)[:8]

    async def body(smap: SprintMap) -> list[int]:
        batcher = FrameBatcher(smap, MapGate(), k=5, window_s=0.5, max_frames=64)
        sessions = [Session(None, smap.localizer(), smap.config.dim) for _ in range(4)]
        sizes: list[int] = []

        async def batch_of(frames: list[tuple[Session, np.ndarray]], late: int = 0) -> None:
            futures = [batcher.submit(s, r) for s, r in frames[: len(frames) - late]]
            if late:  # the other group's frames come 50 ms later
                await asyncio.sleep(0.05)
                futures += [batcher.submit(s, r) for s, r in frames[-late:]]
            await asyncio.gather(*futures)
            sizes.append(batcher.stats.last_size)

        # Queued before the thread starts: the first four frames make one batch.
        first = [batcher.submit(s, r) for s, r in zip(sessions, rows[:4], strict=True)]
        batcher.start()
        try:
            await asyncio.gather(*first)
            sizes.append(batcher.stats.last_size)
            await batch_of(list(zip(sessions[:2], rows[4:6], strict=True)))  # half the fleet
            await batch_of(list(zip(sessions, rows[4:8], strict=True)), late=2)
        finally:
            batcher.stop()
        return sizes

    with SprintMap.open(one_drive_map) as smap:
        sizes = asyncio.run(body(smap))
    # 2 after 4 (the window ran out); then 4 again, not the 2 that came first
    assert sizes == [4, 2, 4]
