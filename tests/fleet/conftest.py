"""A real Ray runtime for the fleet tests: a simulated 3-node cluster, started once.

``ray.cluster_utils.Cluster`` runs a head and two worker nodes (one CPU each) as real Ray
processes on this machine; the tests' driver joins it. Started once per session (~8 s on the
test machine under load) and shared by every test of ``tests/fleet``; tests that kill actors or
workers kill only their own.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

ray = pytest.importorskip("ray", reason="the ray extra is not installed")

NODES = 3


@pytest.fixture(scope="session")
def cluster() -> Iterator[Any]:
    """The running 3-node cluster (``ray.init`` joined it); yields the Cluster."""
    from ray.cluster_utils import Cluster

    if ray.is_initialized():
        ray.shutdown()
    c = Cluster(initialize_head=True,
                head_node_args={"num_cpus": 1, "include_dashboard": False})
    for _ in range(NODES - 1):
        c.add_node(num_cpus=1)
    ray.init(address=c.address, log_to_driver=False, logging_level="ERROR")
    c.wait_for_nodes()
    try:
        yield c
    finally:
        ray.shutdown()
        c.shutdown()
