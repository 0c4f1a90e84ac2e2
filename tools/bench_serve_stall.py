"""Starve ``sprint-map serve`` before authentication and measure what it costs (issue 14, item 5).

Starts a real ``sprint-map serve`` (with a bearer token) on a small map on 127.0.0.1, lets a
vehicle stream frames, then attacks it the ways the issue names, all from loopback and bounded
in count, bytes and time:

- ``--connections`` (600) connections that send a request line and one header, then nothing;
- one header line of ``--header-mib`` (150) MiB, sent until the server closes the connection;
- ``--bodies`` (64) unauthenticated requests declaring 4 MiB bodies, then sending them.

It reports ``/healthz`` latency on fresh connections and the vehicle's frame latency during the
attack, whether a new session can be created, how many header bytes the server took before
closing, the answers to the bodies, the server's RSS growth (``/proc/PID/status`` VmRSS), and
how many stalled connections are still open once the header timeout passed::

    python tools/bench_serve_stall.py [--connections 600] [--target serve|view|both] [--json OUT]

``--target view`` attacks ``sprint-map view`` with a token the same way (its client reads the
overview; the page is its liveness probe); ``both`` runs serve then view, side by side.

The helpers are also what ``tests/server/test_starvation.py`` uses.
"""

from __future__ import annotations

import argparse
import errno
import ipaddress
import json
import os
import selectors
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

STALL_REQUEST = b"POST /v1/sessions HTTP/1.1\r\nHost: 127.0.0.1\r\n"


def address(url: str) -> tuple[str, int]:
    """``(host, port)`` of a loopback ``http://`` URL; anything else is refused."""
    parts = urlsplit(url)
    host = parts.hostname or ""
    if not ipaddress.ip_address(host).is_loopback:
        raise ValueError(f"only loopback addresses are attacked here, not {host}")
    return host, int(parts.port or 80)


def rss_bytes(pid: int) -> int:
    """Resident set size of process ``pid`` (Linux)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError(f"no VmRSS for pid {pid}")


def open_stalled(host: str, port: int, count: int, request: bytes = STALL_REQUEST
                 ) -> list[socket.socket]:
    """``count`` connections that sent ``request`` (a request line and one header) and stop."""
    socks = []
    for _ in range(count):
        sock = socket.create_connection((host, port), timeout=5)
        sock.sendall(request)
        socks.append(sock)
    return socks


def read_all(sock: socket.socket, timeout: float = 10.0) -> bytes:
    """Everything the server sends until it closes (or ``timeout`` passes, or a reset)."""
    sock.settimeout(timeout)
    chunks = []
    try:
        while chunk := sock.recv(65536):
            chunks.append(chunk)
    except (TimeoutError, ConnectionResetError):
        pass
    return b"".join(chunks)


def healthz_seconds(host: str, port: int, path: str = "/healthz") -> float:
    """Time for ``GET /healthz`` (or ``path``) on a fresh connection; raises unless 200."""
    start = time.perf_counter()
    with socket.create_connection((host, port), timeout=10) as sock:
        sock.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n"
                     .encode())
        answer = read_all(sock)
    elapsed = time.perf_counter() - start
    if not answer.startswith(b"HTTP/1.1 200"):
        raise AssertionError(f"{path} answered {answer[:120]!r} after {elapsed:.3f} s")
    return elapsed


def huge_header(host: str, port: int, nbytes: int, timeout: float = 5.0) -> tuple[int, bytes]:
    """Send one header line of up to ``nbytes``; ``(bytes sent before the server closed,
    what it answered)``. Sending stops at the first error (the server closed) or ``timeout``."""
    sent = 0
    with socket.create_connection((host, port), timeout=timeout) as sock:
        sock.sendall(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Big: ")
        chunk = b"a" * 65536
        deadline = time.monotonic() + timeout
        try:
            while sent < nbytes and time.monotonic() < deadline:
                sent += sock.send(chunk[: nbytes - sent])
        except (BrokenPipeError, ConnectionResetError, TimeoutError):
            pass
        return sent, read_all(sock, timeout=1.0)


def unauthenticated_bodies(host: str, port: int, count: int, size: int,
                           path: str = "/v1/sessions/x/frames", timeout: float = 5.0
                           ) -> list[bytes]:
    """``count`` requests without a token declaring ``size``-byte bodies: the headers go
    first and each answer is read (a server that reads bodies first does not answer; after
    ``timeout`` that answer is b""), then every body is pushed as far as the server takes it."""
    socks = []
    head = (f"POST {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: image/png\r\n"
            f"Content-Length: {size}\r\n\r\n").encode()
    for _ in range(count):
        sock = socket.create_connection((host, port), timeout=5)
        sock.sendall(head)
        socks.append(sock)
    answers = {s: b"" for s in socks}
    deadline = time.monotonic() + timeout
    with selectors.DefaultSelector() as waiting:  # (select() stops at descriptor 1024)
        for sock in socks:
            waiting.register(sock, selectors.EVENT_READ)
        while waiting.get_map() and time.monotonic() < deadline:
            for key, _ in waiting.select(max(0.0, deadline - time.monotonic())):
                sock = key.fileobj  # type: ignore[assignment]
                try:
                    chunk = sock.recv(65536)
                except ConnectionResetError:
                    chunk = b""
                answers[sock] += chunk
                if not chunk or b"\r\n\r\n" in answers[sock]:
                    waiting.unregister(sock)
    body = b"\0" * size
    for sock in socks:  # then the bodies, as far as each connection takes them
        sock.setblocking(False)
        try:
            sock.send(body)
        except OSError as exc:
            if exc.errno not in (errno.EPIPE, errno.ECONNRESET, errno.EAGAIN):
                raise
    out = [answers[s] for s in socks]
    for sock in socks:
        sock.close()
    return out


def count_open(socks: list[socket.socket]) -> int:
    """How many of ``socks`` the server has not closed (reads what is pending, no waiting)."""
    still = 0
    for sock in socks:
        sock.setblocking(False)
        try:
            while True:
                chunk = sock.recv(65536)
                if not chunk:
                    break  # closed
        except BlockingIOError:
            still += 1
        except OSError:
            pass  # reset: closed
    return still


def _serve(map_path: Path, token: str, log: Path, config: dict[str, Any], target: str = "serve"
           ) -> tuple[subprocess.Popen[str], str]:
    """``sprint-map serve`` (with ``config``) or ``sprint-map view`` (its defaults: the same
    ServerConfig limits, header timeout 10 s) on a free loopback port, with ``token``."""
    cfg = log.with_suffix(".json")
    cfg.write_text(json.dumps(config))
    extra = ["--config", str(cfg)] if target == "serve" else []
    proc = subprocess.Popen(
        [sys.executable, "-c", "from sprint_map.cli.main import main; main()", target,
         str(map_path), "--host", "127.0.0.1", "--port", "0", *extra],
        stdout=subprocess.PIPE, stderr=log.open("w"), text=True,
        env={**os.environ, "SPRINT_MAP_TOKEN": token})
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if not line.startswith(("serving ", "viewing ")):
        raise RuntimeError(f"server did not start: {line!r} {log.read_text()}")
    return proc, line.split(" on ", 1)[1].split()[0]


def run(connections: int, header_mib: int, bodies: int, header_timeout_s: float,
        target: str = "serve") -> dict[str, Any]:
    """The attack on ``target`` (``serve``, or ``view``: its client reads the overview, its
    liveness probe is the page, its header timeout the default 10 s)."""
    import httpx
    import numpy as np

    from sprint_map.config import MapConfig
    from sprint_map.map import SprintMap

    token = "bench-token"
    auth = {"authorization": f"Bearer {token}"}
    rng = np.random.default_rng(1)
    places = rng.standard_normal((200, 64))

    def noisy() -> np.ndarray:
        x = places + 0.3 * rng.standard_normal(places.shape)
        return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "m.map"
        with SprintMap.create(path, MapConfig(dim=64)) as m:
            m.ingest(noisy(), name="first")
        view = target == "view"
        if view:
            header_timeout_s = 10.0  # ServerConfig's default: view has no --config
        proc, url = _serve(path, token, Path(tmp) / f"{target}.log",
                           {"header_timeout_s": header_timeout_s}, target)
        try:
            host, port = address(url)
            with httpx.Client(base_url=url, headers=auth, timeout=30) as vehicle:
                deadline = time.monotonic() + 60
                while vehicle.get("/" if view else "/readyz").status_code != 200:
                    if time.monotonic() > deadline:
                        raise RuntimeError("server not ready")
                    time.sleep(0.05)
                rows = noisy()
                sid = "" if view else vehicle.post("/v1/sessions").json()["session_id"]

                def frames(lo: int, hi: int) -> list[float]:
                    out = []
                    for i in range(lo, hi):
                        t = time.perf_counter()
                        r = vehicle.get("/viewer/api/overview") if view else vehicle.post(
                            f"/v1/sessions/{sid}/frames",
                            json={"descriptor": rows[i % len(rows)].tolist()})
                        if r.status_code != 200:
                            raise AssertionError(f"frame {i}: {r.status_code} {r.text}")
                        out.append(time.perf_counter() - t)
                    return out

                before_frames = frames(0, 30)
                base = rss_bytes(proc.pid)
                t0 = time.monotonic()
                stalled = open_stalled(host, port, connections, STALL_REQUEST.replace(
                    b"POST /v1/sessions", b"GET /viewer/api/overview") if view else STALL_REQUEST)
                opened_s = time.monotonic() - t0
                health = [healthz_seconds(host, port, "/" if view else "/healthz")
                          for _ in range(10)]
                during_frames = frames(30, 90)
                created = httpx.get(f"{url}/viewer/api/overview", headers=auth, timeout=30
                                    ).status_code if view else httpx.post(
                    f"{url}/v1/sessions", headers=auth, timeout=30).status_code
                rss_stalled = rss_bytes(proc.pid) - base
                sent, answer = huge_header(host, port, header_mib << 20)
                answers = unauthenticated_bodies(host, port, bodies, 4 << 20)
                rss_after = rss_bytes(proc.pid) - base
                time.sleep(max(0.0, t0 + header_timeout_s + 1.5 - time.monotonic()))
                left = count_open(stalled)
                for sock in stalled:
                    sock.close()
                if not view:
                    vehicle.post(f"/v1/sessions/{sid}/commit")
        finally:
            proc.terminate()
            proc.wait(60)

    def ms(values: list[float]) -> dict[str, float]:
        return {"median_ms": round(statistics.median(values) * 1e3, 2),
                "max_ms": round(max(values) * 1e3, 2)}

    return {
        "target": target, "stalled_connections": connections, "open_seconds": round(opened_s, 3),
        "healthz": ms(health), "frames_before": ms(before_frames),
        "frames_during": ms(during_frames), "new_session_status": created,
        "header_bytes_sent_before_close": sent, "header_answer": answer[:40].decode("latin-1"),
        "unauthenticated_bodies": bodies,
        "bodies_answered_401": sum(a.startswith(b"HTTP/1.1 401") for a in answers),
        "rss_delta_mib_stalled": round(rss_stalled / 2**20, 1),
        "rss_delta_mib_all": round(rss_after / 2**20, 1),
        "header_timeout_s": header_timeout_s, "stalled_open_after_timeout": left,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--connections", type=int, default=600)
    parser.add_argument("--header-mib", type=int, default=150)
    parser.add_argument("--bodies", type=int, default=64)
    parser.add_argument("--header-timeout", type=float, default=5.0)
    parser.add_argument("--target", choices=["serve", "view", "both"], default="serve",
                        help="attack sprint-map serve, sprint-map view (with a token), or both "
                             "in turn (the baseline: serve's figures beside view's)")
    parser.add_argument("--json", type=Path, help="write the results here")
    args = parser.parse_args(argv)
    targets = ["serve", "view"] if args.target == "both" else [args.target]
    results = [run(args.connections, args.header_mib, args.bodies, args.header_timeout, t)
               for t in targets]
    width = max(map(len, results[0]))
    for key in results[0]:
        print(f"{key:<{width}}  " + "  ".join(f"{str(r[key]):<40}" for r in results).rstrip())
    if args.json:
        args.json.write_text(json.dumps(results if len(results) > 1 else results[0], indent=2)
                             + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
