"""Sessions with a lag: each frame answers the one posted ``lag`` frames before, the commit
answers the rest, the answers equal the offline ``localize --lag``; bad lags are 4xx."""

from __future__ import annotations

from typing import Any

import httpx
import numpy as np
import pytest

from sprint_map.localize.lagged import MAX_LAG
from sprint_map.map import SprintMap
from sprint_map.server.errors import busy
from sprint_map.server.service import LocalisationService
from tests.helpers.serve import run_service
from tests.helpers.worlds import drive

LAG = 4


async def post_all(client: httpx.AsyncClient, sid: str, rows: np.ndarray, raw: bool
                   ) -> list[dict[str, Any]]:
    out = []
    for row in rows:
        if raw:
            response = await client.post(f"/v1/sessions/{sid}/frames",
                                         content=np.asarray(row, "<f4").tobytes(),
                                         headers={"content-type": "application/octet-stream"})
        else:
            response = await client.post(f"/v1/sessions/{sid}/frames",
                                         json={"descriptor": row.tolist()})
        assert response.status_code == 200, response.text
        out.append(response.json())
    return out


@pytest.mark.parametrize("batching", [64, 0], ids=["batched", "one-at-a-time"])
def test_lagged_session_answers_late_and_flushes_at_commit(one_drive_map, places, rng,
                                                           batching):
    rows = drive(places, rng)[:30]
    with SprintMap.open(one_drive_map, readonly=True) as m:
        offline, _ = m.localize(rows, lag=LAG)
        causal, _ = m.localize(rows)

    async def body(service: LocalisationService, client: httpx.AsyncClient) -> None:
        created = await client.post("/v1/sessions", json={"name": "lagged", "lag": LAG})
        assert created.status_code == 201, created.text
        sid = created.json()["session_id"]
        plain = (await client.post("/v1/sessions")).json()["session_id"]
        answers = await post_all(client, sid, rows, raw=batching > 0)
        at_once = await post_all(client, plain, rows, raw=batching > 0)
        # none yet for the first LAG frames, then frame t answers frame t - LAG
        assert all(a["frame"] is None and a["seq_id"] is None and a["prob"] is None
                   for a in answers[:LAG])
        assert [a["frame"] for a in answers[LAG:]] == list(range(len(rows) - LAG))
        assert [a["frame"] for a in at_once] == list(range(len(rows)))  # lag 0 as before
        done = await client.post(f"/v1/sessions/{sid}/commit")
        assert done.status_code == 200, done.text
        tail = done.json()["decisions"]
        assert [a["frame"] for a in tail] == list(range(len(rows) - LAG, len(rows)))
        got = [(a["seq_id"], a["image_id"], a["prob"]) for a in answers[LAG:] + tail]
        assert got == [(d.seq_id, d.image_id, round(d.prob, 6)) for d in offline]
        plain_done = (await client.post(f"/v1/sessions/{plain}/commit")).json()
        assert "decisions" not in plain_done  # a session without a lag: unchanged answer
        assert [(a["seq_id"], a["image_id"]) for a in at_once] == [
            (d.seq_id, d.image_id) for d in causal]
        # the lagged drive was committed whole, merged from its whole-drive decisions
        assert done.json()["frames"] == len(rows)

    run_service(one_drive_map, body, batch_max_frames=batching)


@pytest.mark.parametrize("lag", [-1, MAX_LAG + 1, 2.5, True, "3"])
def test_a_bad_lag_is_a_4xx_in_the_api_format(one_drive_map, lag):
    async def body(service: LocalisationService, client: httpx.AsyncClient) -> None:
        response = await client.post("/v1/sessions", json={"lag": lag})
        assert response.status_code == 422, response.text
        assert set(response.json()) == {"error", "message"}
        assert "lag" in response.json()["message"]
        assert len(service.registry) == 0

    run_service(one_drive_map, body)


def test_ray_sessions_refuse_a_lag_with_a_clear_error(one_drive_map):
    async def body(service: LocalisationService, client: httpx.AsyncClient) -> None:
        service.localizers = lambda: None  # as serve --ray sets it (never called here)
        response = await client.post("/v1/sessions", json={"lag": 3})
        assert response.status_code == 422
        assert response.json()["error"] == "lag_not_supported"

    run_service(one_drive_map, body)


@pytest.mark.parametrize("batching", [64, 0], ids=["batched", "one-at-a-time"])
def test_a_refused_commit_changes_nothing(one_drive_map, places, rng, batching):
    """A lagged session's commit refused with 503 (the writer's queue full) flushes nothing:
    the frames posted after it and the retried commit answer exactly as ``localize --lag``."""
    rows = drive(places, rng)[:60]
    with SprintMap.open(one_drive_map, readonly=True) as m:
        offline, _ = m.localize(rows, lag=LAG)

    async def body(service: LocalisationService, client: httpx.AsyncClient) -> None:
        sid = (await client.post("/v1/sessions", json={"lag": LAG})).json()["session_id"]
        answers = await post_all(client, sid, rows[:30], raw=batching > 0)
        submit = service.writer.submit

        def refuse(job: Any) -> Any:
            raise busy("1 commits are already waiting; retry later")

        service.writer.submit = refuse  # type: ignore[method-assign]
        refused = await client.post(f"/v1/sessions/{sid}/commit")
        assert refused.status_code == 503, refused.text
        service.writer.submit = submit  # type: ignore[method-assign]
        session = service.registry.get(sid)
        assert session.state == "open" and session.frames == 30
        assert len(session.decisions) == 30 - LAG and session.lagged.waiting == LAG
        answers += await post_all(client, sid, rows[30:], raw=batching > 0)
        done = await client.post(f"/v1/sessions/{sid}/commit")
        assert done.status_code == 200, done.text
        assert done.json()["frames"] == len(rows)
        got = [(a["frame"], a["seq_id"], a["image_id"], a["prob"])
               for a in answers[LAG:] + done.json()["decisions"]]
        assert got == [(d.frame, d.seq_id, d.image_id, round(d.prob, 6)) for d in offline]

    run_service(one_drive_map, body, batch_max_frames=batching)


def test_a_lagged_session_counts_its_waiting_beliefs(one_drive_map, places, rng):
    """``max_buffered_bytes`` counts every buffer a session holds: a lagged session's
    waiting beliefs too, so such a session is refused (503) where its descriptors alone
    would fit; a commit frees all it held."""
    rows = drive(places, rng)[:40]

    async def body(service: LocalisationService, client: httpx.AsyncClient) -> None:
        sid = (await client.post("/v1/sessions", json={"lag": 30})).json()["session_id"]
        await post_all(client, sid, rows[:20], raw=True)
        session = service.registry.get(sid)
        held = session.lagged.smoother.held_bytes
        assert held > 20 * rows.shape[1] * 4  # far more than its descriptors
        assert service.registry.buffered_bytes == session.nbytes >= 20 * 4 * rows.shape[1] + held
        service.registry.max_buffered_bytes = session.nbytes + 4 * rows.shape[1] + 1
        refused = await client.post(f"/v1/sessions/{sid}/frames",
                                    content=np.asarray(rows[20], "<f4").tobytes(),
                                    headers={"content-type": "application/octet-stream"})
        assert refused.status_code == 503, refused.text
        assert session.frames == 20 and service.registry.buffered_bytes == session.nbytes
        service.registry.max_buffered_bytes = 2 << 30
        await post_all(client, sid, rows[20:], raw=True)
        assert (await client.post(f"/v1/sessions/{sid}/commit")).status_code == 200
        assert service.registry.buffered_bytes == 0

    run_service(one_drive_map, body)
