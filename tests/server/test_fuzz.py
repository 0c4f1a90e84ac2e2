"""Fuzz the API with schemathesis, from the running server's own OpenAPI schema: no 5xx.

Every operation gets generated requests, valid and invalid by the schema (both generation
modes); half of those on a
session path use a real open session, so frames reach the filter and commits the writer. The
server is a real ``sprint-map serve`` process.
"""

from __future__ import annotations

import itertools

import httpx
import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis import GenerationMode
from schemathesis.checks import not_a_server_error, status_code_conformance

from sprint_map.config import MapConfig
from sprint_map.map import SprintMap
from tests.helpers.serve import ServerProcess
from tests.helpers.worlds import drive

DIM = 8


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    import numpy as np

    root = tmp_path_factory.mktemp("fuzz")
    rng = np.random.default_rng(7)
    with SprintMap.create(root / "m.map", MapConfig(dim=DIM)) as m:
        m.ingest(drive(rng.standard_normal((50, DIM)), rng), name="first")
    proc = ServerProcess(root / "m.map", root / "server.log",
                         {"max_request_bytes": 65536}).wait_ready()
    yield proc
    assert proc.terminate() == 0
    assert "Traceback" not in proc.stderr(), proc.stderr()


def test_no_server_error(server):
    schema = schemathesis.openapi.from_url(f"{server.url}/openapi.json")
    operations = [result.ok() for result in schema.get_all_operations()]
    assert {(op.method.upper(), op.path) for op in operations} >= {
        ("POST", "/v1/sessions"), ("POST", "/v1/sessions/{session_id}/frames"),
        ("POST", "/v1/sessions/{session_id}/commit"), ("DELETE", "/v1/sessions/{session_id}"),
        ("GET", "/v1/map"), ("GET", "/healthz"), ("GET", "/readyz"), ("GET", "/metrics")}
    statuses: list[int] = []
    made: list[int] = []
    with httpx.Client(base_url=server.url, timeout=30) as client:
        for operation, mode in itertools.product(operations, GenerationMode):
            strategy = operation.as_strategy(generation_mode=mode)
            examples = 24 if operation.path.endswith("/frames") else 8

            @given(case=strategy)
            @settings(max_examples=examples, deadline=None, derandomize=True, database=None,
                      suppress_health_check=list(HealthCheck))
            def fuzz(case):
                made.append(1)
                if "session_id" in (case.path_parameters or {}) and len(made) % 2:
                    real = client.post("/v1/sessions").json()["session_id"]
                    for _ in range(len(made) % 3):  # so that some commits have frames
                        client.post(f"/v1/sessions/{real}/frames",
                                    json={"descriptor": [0.5] * DIM})
                    case.path_parameters["session_id"] = real
                response = case.call_and_validate(
                    checks=[not_a_server_error, status_code_conformance])
                statuses.append(response.status_code)

            try:
                fuzz()
            except Unsatisfiable:  # no invalid request exists (e.g. GET /healthz)
                assert mode is GenerationMode.NEGATIVE
    assert 200 in statuses and 422 in statuses  # valid frames were answered, bad ones refused
