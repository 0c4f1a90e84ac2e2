"""Fixtures of the service tests (helpers in ``tests/helpers/serve.py``)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sprint_map.config import MapConfig
from sprint_map.map import SprintMap
from tests.helpers.serve import DIM, PLACES, ServerProcess
from tests.helpers.worlds import drive


@pytest.fixture
def start_server(tmp_path: Path) -> Iterator[Any]:
    """``start_server(map_path, config=None, ...)`` -> a ready :class:`ServerProcess`."""
    started: list[ServerProcess] = []

    def start(map_path: Path, config: dict[str, Any] | None = None, *, ready: bool = True,
              **kwargs: Any) -> ServerProcess:
        server = ServerProcess(map_path, tmp_path / f"server{len(started)}.log", config,
                               **kwargs)
        started.append(server)
        return server.wait_ready() if ready else server

    yield start
    for server in started:
        if server.proc.poll() is None:
            server.kill()


@pytest.fixture
def places(rng: np.random.Generator) -> np.ndarray:
    return rng.standard_normal((PLACES, DIM))


@pytest.fixture
def one_drive_map(tmp_path: Path, places: np.ndarray, rng: np.random.Generator) -> Path:
    """A precomputed-descriptor map holding one drive over ``places``."""
    path = tmp_path / "city.map"
    with SprintMap.create(path, MapConfig(dim=DIM)) as m:
        m.ingest(drive(places, rng), name="first")
    return path


