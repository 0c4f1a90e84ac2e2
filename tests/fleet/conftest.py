"""A real Ray runtime for the fleet tests: a simulated 3-node cluster, started once.

``ray.cluster_utils.Cluster`` runs a head and two worker nodes (one CPU each) as real Ray
processes on this machine; the tests' driver joins it. It is started by the first test that asks
for it (~8 s on the test machine under load), shared by the tests of ``tests/fleet``, and shut
down as soon as the run leaves this directory (the rest of the suite does not carry a dozen
idle Ray processes). Tests that kill actors or workers kill only this cluster's
(:func:`tests.helpers.fleet.processes_titled` with its raylets).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

ray = pytest.importorskip("ray", reason="the ray extra is not installed")

NODES = 3
HERE = Path(__file__).resolve().parent
_running: list[Any] = []


def _start() -> Any:
    from ray.cluster_utils import Cluster

    if ray.is_initialized():
        ray.shutdown()
    c = Cluster(initialize_head=True,
                head_node_args={"num_cpus": 1, "include_dashboard": False})
    for _ in range(NODES - 1):
        c.add_node(num_cpus=1)
    ray.init(address=c.address, log_to_driver=False, logging_level="ERROR")
    c.wait_for_nodes()
    return c


def _stop() -> None:
    while _running:
        c = _running.pop()
        ray.shutdown()
        c.shutdown()


@pytest.fixture
def cluster() -> Any:
    """The running 3-node cluster (``ray.init`` joined it)."""
    if not _running:
        _running.append(_start())
    return _running[0]


def pytest_runtest_teardown(item: pytest.Item, nextitem: pytest.Item | None) -> None:
    if _running and (nextitem is None or HERE not in Path(str(nextitem.path)).parents):
        _stop()


def pytest_sessionfinish() -> None:
    _stop()
