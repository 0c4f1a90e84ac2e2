"""``sprint-map view`` beside writers and hostile clients (issue 29 items 6, 8, 9): the live
generation followed, an unknown drive a 404, serve's connection guard and Host check."""

from __future__ import annotations

import contextlib
import socket
import time

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from sprint_map.errors import UnknownSequenceError
from sprint_map.map import SprintMap
from sprint_map.viewer.app import create_view_app
from sprint_map.viewer.overview import MapOverview
from tests.helpers.browser import ViewProcess
from tests.helpers.road_map import build_road_map


@pytest.fixture
def road_map(tmp_path, rng):
    build_road_map(tmp_path / "m", rng, drives=3, frames=40)
    return tmp_path / "m"


def _data_dirs(path):
    """The generations holding data: the top level (no CURRENT yet) and gen-N directories."""
    return sorted(p.name for p in path.iterdir() if p.name.startswith("gen-")) + (
        ["top"] if (path / "map.lmdb").exists() else [])


def test_view_follows_compaction_and_releases_the_old_generation(road_map, tmp_path, rng):
    """Was: after ``compact`` and an ingest the new drive was 404, the counts stale, and the
    old generation stayed on disk while the viewer ran."""
    with ViewProcess(road_map, log=tmp_path / "log") as view:
        api = view.url + "/viewer/api"
        assert httpx.get(api + "/overview", timeout=30).json()["counts"]["sequences"] == 4
        with SprintMap.open(road_map) as m:
            m.remove_sequences(["drive-0"])
            m.compact()
            new = m.add_sequence(rng.standard_normal((25, m.config.dim)).astype(np.float32),
                                 name="after-compact").sequence.seq_id
        counts = httpx.get(api + "/overview", timeout=30).json()["counts"]
        assert counts["sequences"] == 4  # 4 - 1 + 1
        assert httpx.get(f"{api}/sequences/{new}", timeout=30).status_code == 200
        assert httpx.get(f"{api}/sequences/0", timeout=30).status_code == 404
        with SprintMap.open(road_map):  # the next writer removes what no reader holds
            pass
        assert _data_dirs(road_map) == ["gen-000001"]
    assert view.proc.returncode == 0


def test_a_drive_removed_during_a_request_is_a_404(road_map, monkeypatch):
    """Was: 500 UnknownSequenceError when another process removed the drive meanwhile."""
    with SprintMap.open(road_map, readonly=True) as m:
        client = TestClient(create_view_app(MapOverview(m)), raise_server_exceptions=False)
        assert client.get("/viewer/api/sequences/1").status_code == 200

        def gone(*args, **kwargs):
            raise UnknownSequenceError("no sequence 1 in the map")

        for name in ("edges", "descriptors", "thumbnail_count"):
            monkeypatch.setattr(m, name, gone)
        for route in ("sequences/1", "matrix/1/0", "matrix/0/1"):
            answer = client.get(f"/viewer/api/{route}")
            assert answer.status_code == 404, (route, answer.text)


def _raw(url: str, data: bytes, wait: float = 0.0) -> bytes:
    host, port = url.removeprefix("http://").rsplit(":", 1)
    with socket.create_connection((host, int(port)), timeout=30) as sock:
        with contextlib.suppress(OSError):
            sock.sendall(data)
        time.sleep(wait)
        chunks = []
        while True:
            try:
                chunk = sock.recv(65536)
            except OSError:
                break
            if not chunk:
                break
            chunks.append(chunk)
        return b"".join(chunks)


def test_view_with_a_token_has_serves_connection_guard(road_map, tmp_path):
    """Was: a 50 MB header line buffered before the token check, a partial header open
    after 40 s."""
    with ViewProcess(road_map, log=tmp_path / "log", env={"SPRINT_MAP_TOKEN": "s3cret"}) as view:
        big = b"GET /viewer/api/overview HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Big: " + b"a" * (
            1 << 20)
        assert _raw(view.url, big).startswith(b"HTTP/1.1 431")
        start = time.monotonic()
        answer = _raw(view.url, b"GET /viewer/api/overview HTTP/1.1\r\nHost: x")
        assert answer.startswith(b"HTTP/1.1 408") and time.monotonic() - start < 15
        headers = {"authorization": "Bearer s3cret"}
        assert httpx.get(view.url + "/viewer/api/overview", headers=headers,
                         timeout=30).status_code == 200
        assert httpx.get(view.url + "/viewer/api/overview", timeout=30).status_code == 401


def test_tokenless_view_answers_its_own_host_only(road_map, tmp_path):
    with ViewProcess(road_map, log=tmp_path / "log") as view:
        ok = httpx.get(view.url + "/viewer/api/overview", timeout=30)
        assert ok.status_code == 200
        for host in ("evil.example", "evil.example:8080", "127.0.0.1.evil.example"):
            answer = httpx.get(view.url + "/viewer/api/overview", headers={"host": host},
                               timeout=30)
            assert answer.status_code == 403, host
        port = view.url.rsplit(":", 1)[1]
        assert httpx.get(view.url + "/", headers={"host": f"localhost:{port}"},
                         timeout=30).status_code == 200
