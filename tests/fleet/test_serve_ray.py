"""``sprint-map serve MAP --ray ADDRESS``: sessions in localiser replicas on a 3-node cluster,
the same API and answers; a replica killed ends its sessions only (503 ``replica_lost``); the
serving process (the writer) killed leaves a map that ``check`` passes."""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from sprint_map.map import SprintMap
from tests.helpers.fleet import NOISE, Server, areas_of, base_map, processes_titled, raylets
from tests.helpers.worlds import drive

pytestmark = pytest.mark.ray


def test_replicas_answer_as_in_process_and_a_lost_one_ends_its_sessions_only(
        cluster: object, tmp_path: Path, rng: np.random.Generator) -> None:
    areas = areas_of(rng, 3)
    path = base_map(tmp_path / "m.map", areas, rng)
    rows = drive(areas[0], rng, NOISE)
    other = drive(areas[1], rng, NOISE)
    address = cluster.address  # type: ignore[attr-defined]
    server = Server(path, tmp_path / "serve.log", "--ray", address, "--replicas", "2")
    try:
        a, b = server.session(), server.session()  # round robin: one on each replica
        answers = []
        for row in rows:
            response = server.frame(a, row)
            assert response.status_code == 200, response.text
            answers.append((response.json()["seq_id"], response.json()["image_id"]))
        with SprintMap.open(path, readonly=True) as m:  # what the in-process service answers
            local = m.localizer()
            want = [(d.seq_id, d.image_id) for d in (local.step(r) for r in rows)]
        assert answers == want
        assert sum(s is not None for s, _ in answers) > len(rows) // 2
        assert server.frame(b, other[0]).status_code == 200

        parents = raylets(cluster)
        replicas = processes_titled("ray::ReplicaWorker", parents)
        assert len(replicas) == 2, replicas
        os.kill(replicas[0], signal.SIGKILL)
        deadline = time.monotonic() + 30
        while replicas[0] in processes_titled("ray::ReplicaWorker", parents):
            assert time.monotonic() < deadline
            time.sleep(0.05)
        status = {}
        for name, session, row in (("a", a, rows[0]), ("b", b, other[1])):
            response = server.frame(session, row)
            status[name] = (response.status_code, response.json().get("error"))
        assert sorted(status.values(), key=str) == sorted(
            [(200, None), (503, "replica_lost")], key=str), status
        survivor = a if status["a"][0] == 200 else b
        committed = server.client.post(f"/v1/sessions/{survivor}/commit")
        assert committed.status_code == 200, committed.text
        c = server.session()  # a new session works (the pool replaced the dead replica)
        for row in other[:3]:
            assert server.frame(c, row).status_code == 200

        # the writer (the serving process) killed while it commits
        def commit_c() -> None:
            with contextlib.suppress(httpx.TransportError):  # killed before it answered
                server.client.post(f"/v1/sessions/{c}/commit")

        commit = threading.Thread(target=commit_c)
        commit.start()
        time.sleep(0.01)
        server.proc.send_signal(signal.SIGKILL)
        server.proc.wait(60)
        commit.join()
    finally:
        server.close()
    with SprintMap.open(path, readonly=True) as m:
        assert m.check().ok
        assert len(m.sequences()) in (4, 5)  # the survivor's drive, and c's if it made it
