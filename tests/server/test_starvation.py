"""The service cannot be starved before authentication (issue 14, item 5), on a real
``sprint-map serve`` over loopback.

Before: 600 connections that sent a request line and one header made ``/healthz`` and ``POST
/v1/sessions`` answer 503 (uvicorn's ``limit_concurrency`` counted them), partial headers never
timed out, a header line was buffered whole, and 64 unauthenticated 4 MiB bodies were read
(+256 MB) before the token was checked. Every socket here goes to 127.0.0.1, and the attack is
bounded in count, bytes and time.
"""

from __future__ import annotations

import socket
import sys
import threading
import time

import httpx
import numpy as np
import pytest

from tests.helpers.worlds import drive
from tools import bench_serve_stall as stall

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="reads the server's RSS from /proc")

TOKEN = "s3cret-token"
AUTH = {"authorization": f"Bearer {TOKEN}"}
STALLED = 600
HEADER_TIMEOUT_S = 4.0


def test_stalled_connections_big_headers_and_unauthenticated_bodies(one_drive_map, places, rng,
                                                                    start_server):
    server = start_server(one_drive_map, {"header_timeout_s": HEADER_TIMEOUT_S},
                          env={"SPRINT_MAP_TOKEN": TOKEN})
    host, port = stall.address(server.url)
    pid = server.proc.pid
    vehicle = httpx.Client(base_url=server.url, headers=AUTH, timeout=10)
    sid = vehicle.post("/v1/sessions").json()["session_id"]
    rows = drive(places, rng)

    def frame(i: int) -> int:
        return vehicle.post(f"/v1/sessions/{sid}/frames",
                            json={"descriptor": rows[i % len(rows)].tolist()}).status_code

    assert [frame(i) for i in range(10)] == [200] * 10  # warm: the baseline RSS includes it
    base_rss = stall.rss_bytes(pid)

    # 600 connections that send a request line and one header, then nothing.
    started = time.monotonic()
    stalled = stall.open_stalled(host, port, STALLED)
    assert len(stalled) == STALLED
    healthz = [stall.healthz_seconds(host, port) for _ in range(5)]
    assert max(healthz) < 1.0, healthz  # was: 503
    assert [frame(i) for i in range(10, 40)] == [200] * 30  # the vehicle keeps going
    fresh = httpx.post(f"{server.url}/v1/sessions", headers=AUTH, timeout=10)
    assert fresh.status_code == 201, fresh.text  # was: 503

    # A header line far beyond the limit is refused once the limit is read, not buffered.
    sent, answer = stall.huge_header(host, port, 32 << 20)
    assert sent < 32 << 20 and (answer.startswith(b"HTTP/1.1 431") or answer == b""), (
        sent, answer[:80])
    # Unauthenticated 4 MiB bodies: answered 401 from the headers, the body never read.
    answers = stall.unauthenticated_bodies(host, port, 64, 4 << 20)
    assert all(a.startswith(b"HTTP/1.1 401") for a in answers), answers[:3]
    grown = stall.rss_bytes(pid) - base_rss
    assert grown < 50 << 20, f"server RSS grew by {grown / 2**20:.1f} MiB"  # was: +256 MB

    # Partial headers time out: the stalled connections still open are closed by the server.
    time.sleep(max(0.0, started + HEADER_TIMEOUT_S + 1.5 - time.monotonic()))
    still_open = stall.count_open(stalled)
    assert still_open == 0, f"{still_open} stalled connections are still open"
    assert [frame(i) for i in range(40, 45)] == [200] * 5
    assert vehicle.post(f"/v1/sessions/{sid}/commit").status_code == 200
    vehicle.close()
    assert server.terminate() == 0
    assert "Traceback" not in server.stderr(), server.stderr()


def test_an_authenticated_slow_body_times_out(one_drive_map, start_server):
    """A body that stops arriving is answered 408 once ``body_timeout_s`` passed."""
    server = start_server(one_drive_map, {"body_timeout_s": 1.0},
                          env={"SPRINT_MAP_TOKEN": TOKEN})
    host, port = stall.address(server.url)
    sid = server.client.post("/v1/sessions", headers=AUTH).json()["session_id"]
    with socket.create_connection((host, port), timeout=10) as sock:
        sock.sendall(f"POST /v1/sessions/{sid}/frames HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                     f"Authorization: Bearer {TOKEN}\r\nContent-Type: application/json\r\n"
                     "Content-Length: 1000\r\n\r\n{\"descriptor\": [".encode())
        start = time.monotonic()
        answer = stall.read_all(sock)
        assert answer.startswith(b"HTTP/1.1 408"), answer[:200]
        assert b'"error":"timeout"' in answer
        assert 0.9 < time.monotonic() - start < 5.0
    # The session is intact and usable.
    ok = server.client.post(f"/v1/sessions/{sid}/frames", headers=AUTH,
                            json={"descriptor": np.full(32, 0.1).tolist()})
    assert ok.status_code == 200 and ok.json()["frame"] == 0
    assert server.terminate() == 0


def test_healthz_answers_while_the_connection_limit_is_full_of_busy_requests(
        one_drive_map, start_server):
    """Connections with a request in progress are never evicted; beyond the limit new ones are
    answered 503 ``busy`` (JSON), but ``/healthz`` still answers."""
    server = start_server(one_drive_map, {"max_connections": 8, "body_timeout_s": 30.0})
    host, port = stall.address(server.url)
    sid = server.client.post("/v1/sessions").json()["session_id"]
    server.client.close()
    busy = []
    for _ in range(8):  # requests whose bodies are not all sent: in progress, not evictable
        sock = socket.create_connection((host, port), timeout=10)
        sock.sendall(f"POST /v1/sessions/{sid}/frames HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                     "Content-Type: application/json\r\nContent-Length: 100\r\n\r\n{".encode())
        busy.append(sock)
    time.sleep(0.3)
    assert stall.healthz_seconds(host, port) < 1.0
    with socket.create_connection((host, port), timeout=10) as sock:
        sock.sendall(b"POST /v1/sessions HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 0\r\n\r\n")
        answer = stall.read_all(sock)
    assert answer.startswith(b"HTTP/1.1 503") and b'"error":"busy"' in answer, answer[:200]
    assert stall.count_open(busy) == 8  # none of the busy ones was dropped
    for sock in busy:
        sock.close()
    threading.Event().wait(0.2)
    with httpx.Client(base_url=server.url, timeout=10) as client:
        assert client.post("/v1/sessions").status_code == 201
    assert server.terminate() == 0
