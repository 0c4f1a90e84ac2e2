"""Regressions of the hardening issue (14) on the service, in process (httpx over ASGI).

A name that is not UTF-8 text is a 4xx (item 9), a decompression bomb is refused from its header
(item 6) and the bearer token is checked before a body is read (item 5; the socket-level limits
are in ``test_starvation.py``). Default names: ``test_session_names.py`` (item 2).
"""

from __future__ import annotations

import asyncio
from typing import Any

import httpx
import numpy as np

from sprint_map.map import SprintMap
from sprint_map.server.service import LocalisationService
from tests.helpers.serve import DIM, run_service

JSON = {"content-type": "application/json"}



def test_names_that_are_not_utf8_text_are_a_4xx(one_drive_map):
    """Item 9: a lone surrogate (valid JSON, not UTF-8 text) in a name was a 500."""

    async def body(service: LocalisationService, client: httpx.AsyncClient) -> None:
        for raw in (b'{"name": "a\\udcffb"}', b'{"name": "\\ud800"}',
                    b'{"name": "x", "\\udcff": 1}', b'{"\\udcff": "x"}'):
            response = await client.post("/v1/sessions", content=raw, headers=JSON)
            assert 400 <= response.status_code < 500, (raw, response.status_code, response.text)
            assert response.json()["error"] in ("bad_input", "bad_payload"), response.text
            assert response.json()["message"]
        sid = (await client.post("/v1/sessions")).json()["session_id"]
        row = ", ".join(["0.5"] * DIM)
        response = await client.post(f"/v1/sessions/{sid}/frames", headers=JSON,
                                     content=f'{{"descriptor": [{row}], "\\udcff": 1}}'.encode())
        assert (response.status_code, response.json()["error"]) == (422, "bad_payload")
        # A good non-ASCII name still works, and is committed as given.
        named = (await client.post("/v1/sessions", json={"name": "vélo-東"})).json()
        rows = np.full((3, DIM), 0.5, np.float32)
        for r in rows:
            await client.post(f"/v1/sessions/{named['session_id']}/frames",
                              json={"descriptor": r.tolist()})
        done = await client.post(f"/v1/sessions/{named['session_id']}/commit")
        assert done.status_code == 200 and done.json()["name"] == "vélo-東"

    run_service(one_drive_map, body)


def test_image_frames_above_the_pixel_limit_are_refused_before_decoding(tmp_path, rng):
    """Item 6: the service's limit (``max_image_pixels``) is read from the image's header."""
    import cv2

    from sprint_map.config import MapConfig

    path = tmp_path / "hog.map"
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (48, 64)).astype(np.float32), (0, 0), 2)
    with SprintMap.create(path, MapConfig.for_descriptor("hog")) as m:
        spec = m.config.descriptor_spec()
        assert spec is not None
        m.add_sequence(np.stack([spec.describe(texture.astype(np.uint8))] * 3), name="first")
    wide = cv2.imencode(".png", np.zeros((1000, 2000), np.uint8))[1].tobytes()  # 2 Mpx, 8 KB
    small = cv2.imencode(".jpg", texture.astype(np.uint8))[1].tobytes()

    async def body(service: LocalisationService, client: httpx.AsyncClient) -> None:
        sid = (await client.post("/v1/sessions")).json()["session_id"]
        refused = await client.post(f"/v1/sessions/{sid}/frames", content=wide,
                                    headers={"content-type": "image/png"})
        assert (refused.status_code, refused.json()["error"]) == (422, "bad_image")
        assert refused.json()["message"] == ("image: PNG image of 2000 x 1000 pixels is larger "
                                             "than the limit of 1000000 pixels (refused before "
                                             "decoding)")
        ok = await client.post(f"/v1/sessions/{sid}/frames", content=small,
                               headers={"content-type": "image/jpeg"})
        assert ok.status_code == 200, ok.text
        gif = await client.post(f"/v1/sessions/{sid}/frames", content=b"GIF89a\x20\x4e\x20\x4e",
                                headers={"content-type": "image/gif"})
        assert (gif.status_code, gif.json()["error"]) == (422, "bad_image")

    run_service(path, body, max_image_pixels=1_000_000)


def test_the_token_is_checked_before_the_body_is_read():
    """Item 5: bodies were buffered (up to 4 MiB each) before the token was checked."""
    from sprint_map.server.app import RequestGuard

    reached: list[str] = []

    async def app(scope: Any, receive: Any, send: Any) -> None:
        reached.append(scope["path"])
        await receive()
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"ok"})

    async def call(path: str, headers: list[tuple[bytes, bytes]]) -> tuple[int, bytes, int]:
        reads = 0

        async def receive() -> dict[str, Any]:
            nonlocal reads
            reads += 1
            return {"type": "http.request", "body": b"x" * 100, "more_body": False}

        sent: list[dict[str, Any]] = []

        async def send(message: dict[str, Any]) -> None:
            sent.append(message)

        guard = RequestGuard(app, limit=1000, token="tok", body_timeout_s=5)
        await guard({"type": "http", "path": path, "method": "POST", "headers": headers},
                    receive, send)
        head = dict(sent[0]["headers"])
        return sent[0]["status"], head.get(b"connection", b""), reads

    lengths = [(b"content-length", b"100")]
    assert asyncio.run(call("/v1/sessions/x/frames", lengths)) == (401, b"close", 0)
    assert asyncio.run(call("/v1/sessions/x/frames", lengths + [
        (b"authorization", b"Bearer nope")])) == (401, b"close", 0)
    assert asyncio.run(call("/v1/sessions/x/frames", [(b"content-length", b"5000"),
                                                       (b"authorization", b"Bearer tok")])
                       ) == (413, b"close", 0)
    assert reached == []
    assert asyncio.run(call("/v1/sessions/x/frames", lengths + [
        (b"authorization", b"Bearer tok")]))[::2] == (200, 1)  # read once, replayed to the app
    assert asyncio.run(call("/healthz", []))[0] == 200  # public paths need no token
    assert reached == ["/v1/sessions/x/frames", "/healthz"]
