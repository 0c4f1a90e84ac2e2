"""SIGKILL a real ``sprint-map serve`` while vehicles stream and commit: nothing acknowledged
is lost.

A client thread runs drive after drive (create a session, stream its frames, commit). The
server is killed right after an acknowledged commit and, once restarted, at a random instant
(inside a commit or between frames). After each kill a writer's open recovers the map; then
every acknowledged drive must be there bit for bit (descriptors), with its merge edges whole
(the service merges the drive's smoothed decisions, re-made at its commit from the hits its
frames retrieved, so the answers alone do not fix them: each edge joins one of the drive's
frames and an earlier drive's image, in both directions with one weight), every other sequence
must be the initial one or a whole drive that was in flight, and ``check`` must pass.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Any

import httpx
import numpy as np

from sprint_map.config import MapConfig
from sprint_map.map import SprintMap
from tests.helpers.serve import DIM
from tests.helpers.worlds import drive

FRAMES = 15


@dataclass
class Fleet:
    """Drives streamed one after the other; what was sent and what was acknowledged."""

    url: str
    places: np.ndarray
    seed: int
    start: int
    sent: dict[str, np.ndarray] = field(default_factory=dict)  # name -> rows, before commit
    answers: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    acked: dict[str, int] = field(default_factory=dict)  # name -> seq id
    ack: threading.Event = field(default_factory=threading.Event)

    def run(self) -> None:
        try:
            with httpx.Client(base_url=self.url, timeout=30) as client:
                for i in range(self.start, self.start + 1000):
                    name = f"drive-{i}"
                    rng = np.random.default_rng([self.seed, i])
                    offset = int(rng.integers(0, len(self.places) - FRAMES))
                    rows = drive(self.places[offset : offset + FRAMES], rng)
                    sid = client.post("/v1/sessions", json={"name": name}).json()["session_id"]
                    self.answers[name] = [
                        client.post(f"/v1/sessions/{sid}/frames",
                                    json={"descriptor": row.tolist()}).json()
                        for row in rows
                    ]
                    self.sent[name] = rows
                    response = client.post(f"/v1/sessions/{sid}/commit")
                    assert response.status_code == 200, response.text
                    self.acked[name] = response.json()["seq_id"]
                    self.ack.set()
        except (httpx.TransportError, ValueError):
            return  # the server was killed


def _verify(path, fleets: list[Fleet], first: np.ndarray) -> int:
    """A writer's open (recovery), then every promise; returns the sequences found."""
    SprintMap.open(path).close()
    with SprintMap.open(path, readonly=True) as m:
        config = m.config
        records = {s.name: s for s in m.sequences()}
        assert m.descriptors(records["first"].seq_id).tobytes() == first.tobytes()
        sent = {name: rows for f in fleets for name, rows in f.sent.items()}
        answers = {name: a for f in fleets for name, a in f.answers.items()}
        acked = {name: seq for f in fleets for name, seq in f.acked.items()}
        for name, seq in acked.items():
            assert records[name].seq_id == seq, name
        edges_by_seq: dict[int, dict[tuple[int, int], tuple[float, int | None]]] = {}
        for e in m.store.edges():
            edges_by_seq.setdefault(e.query_seq, {})[(e.src, e.dst)] = (e.weight, e.frame)
        for name, rec in records.items():
            if name == "first":
                continue
            assert name in sent, f"{name} was never committed by a client"
            assert m.descriptors(rec.seq_id).tobytes() == sent[name].tobytes(), name
            got = edges_by_seq.get(rec.seq_id, {})
            first_v, length = rec.first_vertex, rec.length
            for (src, dst), (weight, frame) in got.items():
                mine = src if first_v <= src < first_v + length else dst
                other = dst if mine == src else src
                assert first_v <= mine < first_v + length and other < first_v, name
                assert frame == mine - first_v and 0 < weight <= 1, name
                if config.merge.both_ways:
                    assert got[(dst, src)][0] == weight, name
            assert len(answers[name]) == length, name
        report = m.check()
        assert report.ok, report.violations
        return len(records)


def test_sigkill_loses_no_acknowledged_commit(tmp_path, places, rng, start_server):
    path = tmp_path / "fleet.map"
    first = drive(places, rng)
    with SprintMap.create(path, MapConfig(dim=DIM)) as m:
        m.ingest(first, name="first")
    fleets: list[Fleet] = []
    seen = 1
    for round_, kill_after in enumerate(("ack", "random")):
        server = start_server(path)
        fleet = Fleet(server.url, places, seed=round_, start=100 * round_)
        fleets.append(fleet)
        client = threading.Thread(target=fleet.run)
        client.start()
        if kill_after == "ack":
            while len(fleet.acked) < 3:  # kill right after the third acknowledgement
                assert fleet.ack.wait(60), server.stderr()
                fleet.ack.clear()
        else:
            assert fleet.ack.wait(60), server.stderr()
            time.sleep(float(rng.uniform(0.0, 0.4)))
        server.kill()
        client.join(60)
        assert fleet.acked, "no commit was acknowledged before the kill"
        found = _verify(path, fleets, first)
        assert found >= seen + len(fleet.acked)
        seen = found
