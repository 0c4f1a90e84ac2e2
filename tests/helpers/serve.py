"""Helpers of the service tests: real ``sprint-map serve`` processes and drives to stream.

:class:`ServerProcess` starts ``sprint-map serve MAP --port 0`` in a subprocess (a real uvicorn
on loopback), reads the port it announces and waits for ``/readyz``; tests talk to it over
HTTP with httpx. (A module of its own, not ``conftest``: ``tests/conftest.py`` has that name.)
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from sprint_map.map import SprintMap
from sprint_map.server.app import create_app
from sprint_map.server.config import ServerConfig
from sprint_map.server.service import LocalisationService

DIM = 32
PLACES = 80
SERVE = [sys.executable, "-c", "from sprint_map.cli.main import main; main()", "serve"]


class ServerProcess:
    """A ``sprint-map serve`` subprocess on a free loopback port."""

    def __init__(self, map_path: Path, log: Path, config: dict[str, Any] | None = None,
                 env: dict[str, str] | None = None, args: tuple[str, ...] = ()) -> None:
        cmd = [*SERVE, str(map_path), "--port", "0", *args]
        if config:
            cfg = log.with_suffix(".config.json")
            cfg.write_text(json.dumps(config))
            cmd += ["--config", str(cfg)]
        self.log = log
        self._stderr = log.open("w")
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=self._stderr, text=True,
                                     env={**os.environ, **(env or {})})
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        assert line.startswith("serving "), f"no announcement: {line!r} {self.stderr()}"
        self.url = line.split(" on ", 1)[1].strip()
        self.client = httpx.Client(base_url=self.url, timeout=60)

    def stderr(self) -> str:
        if not self._stderr.closed:
            self._stderr.flush()
        return self.log.read_text()

    def wait_ready(self, timeout: float = 60.0) -> ServerProcess:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                if self.client.get("/readyz").status_code == 200:
                    return self
            except httpx.TransportError:
                pass
            assert self.proc.poll() is None, f"server died: {self.stderr()}"
            time.sleep(0.02)
        raise AssertionError(f"server not ready after {timeout} s: {self.stderr()}")

    def terminate(self, timeout: float = 60.0) -> int:
        """SIGTERM and wait; returns the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        code = self.proc.wait(timeout)
        self.close()
        return code

    def kill(self) -> None:
        """SIGKILL and reap."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait(60)
        self.close()

    def close(self) -> None:
        self.client.close()
        if self.proc.stdout is not None:
            self.proc.stdout.close()
        self._stderr.close()


def post_frame(client: httpx.Client, session: str, row: np.ndarray) -> httpx.Response:
    return client.post(f"/v1/sessions/{session}/frames", json={"descriptor": row.tolist()})


def stream(client: httpx.Client, session: str, rows: np.ndarray) -> list[dict[str, Any]]:
    """Send every row as a frame; return the answers (all must be 200)."""
    answers = []
    for row in rows:
        response = post_frame(client, session, row)
        assert response.status_code == 200, response.text
        answers.append(response.json())
    return answers


def decisions(answers: list[dict[str, Any]]) -> list[tuple[int | None, int | None]]:
    return [(a["seq_id"], a["image_id"]) for a in answers]


Body = Callable[[LocalisationService, httpx.AsyncClient], Awaitable[Any]]


def run_service(map_path: Path, body: Body, token: str | None = None, **config: Any) -> Any:
    """Open the map, run the service in process, run ``body(service, client)``, close."""

    async def main() -> Any:
        service = LocalisationService(SprintMap.open(map_path), ServerConfig(**config))
        app = create_app(service, token)
        await service.start()
        try:
            async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app),
                                         base_url="http://service", timeout=60) as client:
                return await body(service, client)
        finally:
            await service.shutdown()

    return asyncio.run(main())
