"""The service in process (httpx over ASGI, no socket): map changes reaching live filters,
bounded queues, images on a HoG map, and the pieces (gate, metrics, config, auth).
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Awaitable
from typing import Any

import cv2
import httpx
import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.config import MapConfig
from sprint_map.errors import ConfigError, UnsafeServeError
from sprint_map.frontend.descriptors import DescriptorSpec
from sprint_map.frontend.imagefiles import decode_image
from sprint_map.map import SprintMap
from sprint_map.server.auth import check_bind, is_loopback, load_token, token_matches
from sprint_map.server.config import ServerConfig
from sprint_map.server.gate import MapGate
from sprint_map.server.metrics import Metrics
from sprint_map.server.service import LocalisationService
from tests.helpers.serve import DIM, run_service
from tests.helpers.worlds import drive


async def frames(client: httpx.AsyncClient, sid: str, rows: np.ndarray) -> list[dict[str, Any]]:
    out = []
    for row in rows:
        response = await client.post(f"/v1/sessions/{sid}/frames",
                                     json={"descriptor": row.tolist()})
        assert response.status_code == 200, response.text
        out.append(response.json())
    return out


@pytest.mark.parametrize("first_len", [80, 40], ids=["root-kept", "root-moves"])
def test_live_filters_follow_a_commit_that_merges_their_component(tmp_path, rng, first_len):
    """A drive joins the component a live session is localised in (its id may change)."""
    here, there = rng.standard_normal((first_len, DIM)), rng.standard_normal((40, DIM))
    path = tmp_path / "m.map"
    with SprintMap.create(path, MapConfig(dim=DIM)) as m:
        m.ingest(drive(here, rng), name="here")
        m.ingest(drive(there, rng), name="there", merge=False)  # its own component
        assert len(m.components()) == 2
    watcher_rows = drive(here, rng)
    joiner = np.concatenate([drive(here[:40], rng), drive(there, rng)])

    async def body(service: LocalisationService, client: httpx.AsyncClient) -> None:
        watcher = (await client.post("/v1/sessions")).json()["session_id"]
        before = await frames(client, watcher, watcher_rows[:20])
        assert all(a["seq_id"] == 0 for a in before[5:])
        sid = (await client.post("/v1/sessions")).json()["session_id"]
        await frames(client, sid, joiner)
        done = (await client.post(f"/v1/sessions/{sid}/commit")).json()
        comps = {c.component for c in service.map.components()}
        assert len(comps) == 1 and done["component"] in comps  # all three joined
        # A session started now gets the merged component (not a stale one from the cache).
        fresh = (await client.post("/v1/sessions")).json()["session_id"]
        newer = await frames(client, fresh, watcher_rows[20:])
        assert sum(a["image_id"] == 20 + i for i, a in enumerate(newer)) >= 0.8 * len(newer)
        # The watcher's next frames also hit the new drive's vertices (same places).
        after = await frames(client, watcher, watcher_rows[20:])
        live = service.registry.get(watcher).localizer.filter
        assert set(live.active_component_ids) <= comps
        assert abs(sum(live.component_probs().values()) + live.sink_prob - 1) < 1e-9
        assert sum(a["image_id"] == 20 + i and a["seq_id"] in (0, 2)
                   for i, a in enumerate(after)) >= 0.8 * len(after)

    run_service(path, body)


def test_raw_float32_frames_answer_as_json_frames(one_drive_map, places, rng):
    rows = drive(places, rng)[:30]
    raw = {"content-type": "application/octet-stream"}

    async def body(service: LocalisationService, client: httpx.AsyncClient) -> None:
        a, b = [(await client.post("/v1/sessions")).json()["session_id"] for _ in range(2)]
        as_json = await frames(client, a, rows)
        as_raw = []
        for row in rows:
            response = await client.post(f"/v1/sessions/{b}/frames",
                                         content=row.astype("<f4").tobytes(), headers=raw)
            assert response.status_code == 200, response.text
            as_raw.append(response.json())
        strip = [{k: v for k, v in x.items() if k != "timing"} for x in as_json]
        assert strip == [{k: v for k, v in x.items() if k != "timing"} for x in as_raw]
        for data in (b"\0" * (4 * DIM - 4), np.full(DIM, np.nan, "<f4").tobytes()):
            bad = await client.post(f"/v1/sessions/{b}/frames", content=data, headers=raw)
            assert bad.status_code == 422 and bad.json()["error"] in (
                "descriptor_shape", "invalid_descriptor")
        assert service.metrics.frame_seconds.count(payload="raw") == len(rows)
        # Both sessions localise in the one component: loaded once, into the shared cache.
        assert (service.cache.misses, len(service.cache)) == (1, 1)
        assert service.registry.get(a).localizer.cache is service.cache

    run_service(one_drive_map, body)


def test_bounded_queues_answer_429_and_503(one_drive_map, places, rng):
    rows = drive(places, rng)

    async def body(service: LocalisationService, client: httpx.AsyncClient) -> None:
        sids = [(await client.post("/v1/sessions")).json()["session_id"] for _ in range(4)]
        for sid in sids:
            await frames(client, sid, rows[:3])

        def post(sid: str) -> Awaitable[httpx.Response]:
            return client.post(f"/v1/sessions/{sid}/frames", json={"descriptor": rows[5].tolist()})

        with service.gate.exclusive():  # as a long commit would: frames wait in the workers
            first = asyncio.create_task(post(sids[0]))
            second = asyncio.create_task(post(sids[0]))
            await asyncio.sleep(0.2)
            third = await post(sids[0])  # max_pending_frames=2 of this session are waiting
            assert (third.status_code, third.json()["error"]) == (429, "too_many_pending")
            other = asyncio.create_task(post(sids[1]))
            await asyncio.sleep(0.2)
            refused = await post(sids[2])  # max_queued_frames=3 over all sessions
            assert (refused.status_code, refused.json()["error"]) == (503, "busy")
        answered = [await t for t in (first, second, other)]
        assert [r.status_code for r in answered] == [200, 200, 200]
        assert [r.json()["frame"] for r in answered[:2]] == [3, 4]

    run_service(one_drive_map, body, max_pending_frames=2, max_queued_frames=3)


def test_commit_queue_full_answers_503(one_drive_map, places, rng):
    rows = drive(places, rng)

    async def body(service: LocalisationService, client: httpx.AsyncClient) -> None:
        sids = [(await client.post("/v1/sessions")).json()["session_id"] for _ in range(3)]
        for sid in sids:
            await frames(client, sid, rows[:5])
        with service.gate.exclusive():  # the writer blocks inside its first commit
            running = asyncio.create_task(client.post(f"/v1/sessions/{sids[0]}/commit"))
            await asyncio.sleep(0.3)
            waiting = asyncio.create_task(client.post(f"/v1/sessions/{sids[1]}/commit"))
            await asyncio.sleep(0.3)
            refused = await client.post(f"/v1/sessions/{sids[2]}/commit")
            assert (refused.status_code, refused.json()["error"]) == (503, "busy")
        assert (await running).json()["seq_id"] == 1
        assert (await waiting).json()["seq_id"] == 2
        # The refused session is still open and commits once the queue has room.
        assert (await client.post(f"/v1/sessions/{sids[2]}/commit")).json()["seq_id"] == 3

    run_service(one_drive_map, body, commit_queue_size=1)


def test_quiet_sessions_expire_and_session_limit(one_drive_map):
    zero = {"descriptor": [0.0] * DIM}

    async def body(service: LocalisationService, client: httpx.AsyncClient) -> None:
        sids = [(await client.post("/v1/sessions")).json()["session_id"] for _ in range(2)]
        full = await client.post("/v1/sessions")
        assert (full.status_code, full.json()["error"]) == (503, "busy")
        assert full.headers["retry-after"] == "1"
        for _ in range(8):  # ttl 0.3 s, checked every 0.075 s: the busy session stays
            await asyncio.sleep(0.1)
            kept = await client.post(f"/v1/sessions/{sids[0]}/frames", json=zero)
            assert kept.status_code == 200
        gone = await client.post(f"/v1/sessions/{sids[1]}/frames", json=zero)
        assert (gone.status_code, gone.json()["error"]) == (404, "unknown_session")
        await asyncio.sleep(1.0)
        assert (await client.post(f"/v1/sessions/{sids[0]}/frames", json=zero)
                ).status_code == 404
        assert service.metrics.sessions.value(how="expired") == 2
        assert len(service.registry) == 0 and service.registry.buffered_bytes == 0
        assert (await client.post("/v1/sessions")).status_code == 201

    run_service(one_drive_map, body, session_ttl_s=0.3, max_sessions=2)


def test_bearer_token(one_drive_map):
    async def body(service: LocalisationService, client: httpx.AsyncClient) -> None:
        assert (await client.get("/healthz")).status_code == 200
        assert (await client.get("/readyz")).status_code == 200
        for response in [await client.post("/v1/sessions"), await client.get("/v1/map"),
                         await client.get("/metrics"),
                         await client.post("/v1/sessions",
                                           headers={"authorization": "Bearer wrong"})]:
            assert (response.status_code, response.json()["error"]) == (401, "unauthorised")
            assert response.headers["www-authenticate"] == "Bearer"
        ok = await client.post("/v1/sessions", headers={"authorization": "Bearer s3cret"})
        assert ok.status_code == 201
        schema = (await client.get("/openapi.json")).json()
        assert schema["components"]["securitySchemes"]["HTTPBearer"]["scheme"] == "bearer"

    run_service(one_drive_map, body, token="s3cret")


def test_serve_refuses_a_public_address_without_token(one_drive_map, monkeypatch):
    monkeypatch.delenv("SPRINT_MAP_TOKEN", raising=False)
    result = CliRunner().invoke(main, ["serve", str(one_drive_map), "--host", "0.0.0.0"])
    assert result.exit_code == 18
    assert result.output.startswith("Error: refusing to listen on 0.0.0.0 without a bearer")
    assert len(result.output.strip().splitlines()) == 1


def _textures(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    """``n`` frames of a slowly panning smooth random texture (uint8 gray, 48 x 64)."""
    world = cv2.GaussianBlur(rng.uniform(0, 255, (48, 64 + 4 * n)).astype(np.float32), (0, 0), 2)
    return [np.clip(world[:, 4 * i : 4 * i + 64], 0, 255).astype(np.uint8) for i in range(n)]


def test_image_frames_on_a_hog_map(tmp_path, rng):
    images = _textures(rng, 30)
    folder = tmp_path / "drive"
    folder.mkdir()
    for i, image in enumerate(images):
        cv2.imwrite(str(folder / f"{i:03d}.png"), image)
    path = tmp_path / "hog.map"
    with SprintMap.create(path, MapConfig.for_descriptor("hog")) as m:
        m.ingest(m.open_source(folder).iter_batches(), name="first")
    noisy = [cv2.imencode(".png", np.clip(im + rng.normal(0, 4, im.shape), 0, 255)
                          .astype(np.uint8))[1].tobytes() for im in images]
    jpeg = cv2.imencode(".jpg", images[0])[1].tobytes()

    async def body(service: LocalisationService, client: httpx.AsyncClient) -> dict[str, Any]:
        sid = (await client.post("/v1/sessions")).json()["session_id"]
        answers = []
        for data in noisy:
            response = await client.post(f"/v1/sessions/{sid}/frames", content=data,
                                         headers={"content-type": "image/png"})
            assert response.status_code == 200, response.text
            answers.append(response.json())
        assert sum(a["image_id"] == i for i, a in enumerate(answers)) >= 0.8 * len(answers)
        for data, code in ((b"not an image", "bad_image"), (jpeg[: len(jpeg) // 2], "bad_image"),
                           (b"", "bad_image")):
            bad = await client.post(f"/v1/sessions/{sid}/frames", content=data,
                                    headers={"content-type": "image/jpeg"})
            assert (bad.status_code, bad.json()["error"]) == (422, code), bad.text
        # A JSON descriptor of the map's dimension works on an image map too.
        spec = DescriptorSpec("hog")
        row = spec.describe(images[3])
        ok = await client.post(f"/v1/sessions/{sid}/frames", json={"descriptor": row.tolist()})
        assert ok.status_code == 200 and ok.json()["frame"] == len(noisy)
        result: dict[str, Any] = (await client.post(f"/v1/sessions/{sid}/commit")).json()
        return result

    done = run_service(path, body)
    spec = DescriptorSpec("hog")
    want = np.stack([spec.describe(decode_image(d)) for d in noisy] + [spec.describe(images[3])])
    with SprintMap.open(path, readonly=True) as m:
        assert m.descriptors(done["seq_id"]).tobytes() == want.astype(np.float32).tobytes()


def test_gate_is_writer_preferring():
    gate = MapGate()
    events: list[str] = []
    entered = threading.Event()

    def reader(name: str, hold: float) -> None:
        with gate.shared():
            events.append(f"{name}+")
            entered.set()
            time.sleep(hold)
            events.append(f"{name}-")

    def writer() -> None:
        with gate.exclusive():
            events.append("W")

    first = threading.Thread(target=reader, args=("r1", 0.3))
    first.start()
    entered.wait()
    w = threading.Thread(target=writer)
    w.start()
    time.sleep(0.05)
    late = threading.Thread(target=reader, args=("r2", 0.0))
    late.start()  # arrives while the writer waits: goes after it
    for t in (first, w, late):
        t.join()
    assert events == ["r1+", "r1-", "W", "r2+", "r2-"]
    assert gate.last_exclusive_s < 0.1


def test_metrics_text_format():
    metrics = Metrics()
    metrics.frames.inc(result="match")
    metrics.frames.inc(2, result="no_match")
    for value in (0.0004, 0.003, 0.003, 20.0):
        metrics.frame_seconds.observe(value, payload="descriptor")
    metrics.gauge("sprint_map_test_gauge", "A test gauge.", lambda: 7)
    text = metrics.render()
    lines = text.splitlines()
    assert 'sprint_map_frames_total{result="no_match"} 2' in lines
    assert "# TYPE sprint_map_frame_seconds histogram" in lines
    buckets = [float(line.split()[-1]) for line in lines
               if line.startswith("sprint_map_frame_seconds_bucket")]
    assert buckets == sorted(buckets) and buckets[0] == 1 and buckets[-1] == 4
    assert 'sprint_map_frame_seconds_bucket{payload="descriptor",le="0.005"} 3' in lines
    assert 'sprint_map_frame_seconds_count{payload="descriptor"} 4' in lines
    assert "sprint_map_test_gauge 7" in lines
    assert "sprint_map_commits_total 0" in lines  # a counter never incremented is still shown
    assert text.endswith("\n")


def test_server_config_round_trip_and_validation():
    config = ServerConfig(port=0, max_sessions=3, on_shutdown="commit")
    assert ServerConfig.from_dict(config.to_dict()) == config
    for bad in ({"port": 70000}, {"max_sessions": 0}, {"on_shutdown": "maybe"},
                {"session_ttl_s": 0}, {"frame_workers": True}, {"no_such_option": 1}):
        with pytest.raises(ConfigError):
            ServerConfig.from_dict(bad)


@pytest.mark.parametrize("host,loopback", [("127.0.0.1", True), ("127.8.9.1", True),
                                           ("::1", True), ("localhost", True),
                                           ("0.0.0.0", False), ("::", False),
                                           ("10.0.0.5", False), ("example.org", False)])
def test_loopback_rule(host, loopback):
    assert is_loopback(host) is loopback
    check_bind(host, "token")  # with a token anything goes
    if loopback:
        check_bind(host, None)
    else:
        with pytest.raises(UnsafeServeError):
            check_bind(host, None)


def test_token_sources_and_matching(tmp_path, monkeypatch):
    monkeypatch.delenv("SPRINT_MAP_TOKEN", raising=False)
    assert load_token(ServerConfig()) is None
    monkeypatch.setenv("SPRINT_MAP_TOKEN", " abc ")
    assert load_token(ServerConfig()) == "abc"
    file = tmp_path / "t"
    file.write_text("fromfile\n")
    assert load_token(ServerConfig(token_file=str(file))) == "fromfile"
    assert token_matches("Bearer abc", "abc") and token_matches("bearer abc", "abc")
    assert not token_matches("Bearer abd", "abc") and not token_matches(None, "abc")
    assert not token_matches("Basic abc", "abc")


def test_the_writer_retrains_the_index_beside_the_sessions(tmp_path, rng):
    """A commit that brings the map past ``index_retrain_growth`` times what its approximate
    index was trained on: the writer thread retrains after the commit, sessions go on."""
    places = rng.standard_normal((300, DIM))
    path = tmp_path / "m.map"
    config = MapConfig.from_dict({
        "dim": DIM, "index_type": "ivf-pq", "index_nlist": 8, "index_nprobe": 8,
        "index_segment_rows": 128, "index_merge_factor": 3, "index_train_sample": 1000,
        "index_rerank": 50, "index_retrain_growth": 2.0})
    with SprintMap.create(path, config) as m:
        m.ingest(drive(places, rng), name="first")
        m.search(places[:1], 1)  # the index is loaded (and trained) like a service's
        trained = m.store.index.active.manifest
    assert trained.trained_on == 300
    second = drive(places, rng)

    async def body(service: LocalisationService, client: httpx.AsyncClient) -> None:
        sid = (await client.post("/v1/sessions")).json()["session_id"]
        await frames(client, sid, second)
        done = (await client.post(f"/v1/sessions/{sid}/commit")).json()
        assert done["edges_added"] > 0
        index = service.map.store.index
        for _ in range(200):  # the writer thread retrains after answering the commit
            if index.active.manifest.trained_on > 300:
                break
            await asyncio.sleep(0.05)
        assert index.active.manifest.trained_on == 300 + len(second)
        assert index.active.manifest.generation == trained.generation + 1
        assert index.defer_retrain and any("beside searches" in e for e in index.events)
        watcher = (await client.post("/v1/sessions")).json()["session_id"]
        answers = await frames(client, watcher, drive(places, rng)[:60])
        assert sum(a["seq_id"] is not None for a in answers[10:]) >= 40

    run_service(path, body)
