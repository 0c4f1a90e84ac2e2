"""The HTTP API against real ``sprint-map serve`` processes on loopback.

A vehicle's drive end to end (answers equal the offline ``localize``; the commit equals what
``SprintMap.merge`` commits for those decisions; the next drive localises against it),
concurrent sessions, the error
answers for bad input, limits, metrics and graceful shutdown (expiry and auth: in process).
"""

from __future__ import annotations

import json
import shutil
import signal
import threading

import numpy as np

from sprint_map.map import SprintMap
from tests.helpers.serve import DIM, decisions, post_frame, stream
from tests.helpers.worlds import drive


def _offline(map_path, rows):
    with SprintMap.open(map_path, readonly=True) as m:
        found, _ = m.localize(rows)
    return [(d.seq_id, d.image_id) for d in found], [d.prob for d in found]


def _stored(map_path):
    """Sequences (name, descriptors), edges and components of a map, for comparison."""
    with SprintMap.open(map_path, readonly=True) as m:
        seqs = [(s.name, m.descriptors(s.seq_id).tobytes(),
                 None if m.positions(s.seq_id) is None else m.positions(s.seq_id)[:, :3].tolist())
                for s in m.sequences()]
        edges = sorted((e.src, e.dst, e.weight, e.query_seq, e.frame) for e in m.store.edges())
        comps = sorted((c.component, tuple(c.sequences)) for c in m.components())
        report = m.check()
    return seqs, edges, comps, report


def test_drives_end_to_end_equal_offline_localize_and_ingest(one_drive_map, places, rng,
                                                             start_server, tmp_path):
    second, third = drive(places, rng), drive(places, rng)
    reference = tmp_path / "reference.map"
    shutil.copytree(one_drive_map, reference)
    want, want_prob = _offline(one_drive_map, second)

    server = start_server(one_drive_map)
    c = server.client
    sid = c.post("/v1/sessions", json={"name": "second"}).json()["session_id"]
    where = np.column_stack([np.arange(len(second)) * 1.5, np.arange(len(second)) * -0.5,
                             np.full(len(second), 90.0)])
    answers = []
    for row, pos in zip(second, where, strict=True):  # with positions, as `ingest` takes them
        response = c.post(f"/v1/sessions/{sid}/frames",
                          json={"descriptor": row.tolist(), "position": pos.tolist()})
        assert response.status_code == 200, response.text
        answers.append(response.json())
    assert [a["frame"] for a in answers] == list(range(len(second)))
    # No commit ran meanwhile: the streamed answers are the offline ones, frame by frame.
    assert decisions(answers) == want
    np.testing.assert_allclose([a["prob"] for a in answers], want_prob, atol=1e-6)
    assert sum(a["image_id"] == i for i, a in enumerate(answers)) >= 0.8 * len(second)
    assert {"retrieval_ms", "hmm_ms", "server_ms"} == set(answers[0]["timing"])
    committed = c.post(f"/v1/sessions/{sid}/commit").json()
    assert committed["seq_id"] == 1 and committed["component"] == 0
    assert committed["edges_added"] > 0
    assert c.post(f"/v1/sessions/{sid}/frames", json={"descriptor": [0.0] * DIM}
                  ).status_code == 404  # a committed session is closed

    # The next drive localises against the map including the committed one.
    sid = c.post("/v1/sessions", json={"name": "third"}).json()["session_id"]
    answers = stream(c, sid, third)
    assert {a["seq_id"] for a in answers} >= {1}
    assert sum(a["image_id"] == i for i, a in enumerate(answers)) >= 0.8 * len(third)
    assert c.post(f"/v1/sessions/{sid}/commit").json()["seq_id"] == 2
    info = c.get("/v1/map").json()
    assert server.terminate() == 0

    # The commits are exactly what `ingest` commits for the same drives (the service smooths a
    # drive's decisions at its commit, as ingest does, from the k hits its frames retrieved and
    # a smooth_k-deep search of the drive made then; ingest records both while it streams).
    with SprintMap.open(reference) as m:
        m.ingest(second, name="second", positions=where)
        m.ingest(third, name="third")
    got, expected = _stored(one_drive_map), _stored(reference)
    assert got[0] == expected[0]  # names, descriptors (bit for bit) and positions
    assert got[0][1][2] is not None and got[0][2][2] is None
    assert [e[:3] + e[4:] for e in got[1]] == [e[:3] + e[4:] for e in expected[1]]
    assert got[2] == expected[2]
    assert got[3].ok, got[3].violations
    with SprintMap.open(one_drive_map, readonly=True) as m:
        now = m.info()
    assert set(info) == set(now)
    assert {k: info[k] for k in ("sequences", "vertices", "edges", "components", "dim")} == {
        k: now[k] for k in ("sequences", "vertices", "edges", "components", "dim")}
    assert now["index"]["persisted"] == now["vertices"]  # the shutdown persisted the index


def test_concurrent_sessions_keep_their_own_order_and_state(one_drive_map, places, rng,
                                                            start_server):
    drives = [drive(places, rng) for _ in range(4)]
    offline = [_offline(one_drive_map, d)[0] for d in drives]
    server = start_server(one_drive_map, {"frame_workers": 3})
    c = server.client
    sids = [c.post("/v1/sessions").json()["session_id"] for _ in drives]
    results: dict[int, list] = {}

    def vehicle(i: int) -> None:
        import httpx

        with httpx.Client(base_url=server.url, timeout=60) as own:
            results[i] = stream(own, sids[i], drives[i])

    threads = [threading.Thread(target=vehicle, args=(i,)) for i in range(len(drives))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for i in range(len(drives)):
        assert [a["frame"] for a in results[i]] == list(range(len(drives[i])))
        assert decisions(results[i]) == offline[i]
    # One session commits while the others keep streaming: every frame is still answered.
    extra = [drive(places, rng) for _ in range(3)]
    more: dict[int, list] = {}

    def again(i: int) -> None:
        import httpx

        with httpx.Client(base_url=server.url, timeout=60) as own:
            more[i] = stream(own, sids[i + 1], extra[i])

    threads = [threading.Thread(target=again, args=(i,)) for i in range(3)]
    for t in threads:
        t.start()
    assert c.post(f"/v1/sessions/{sids[0]}/commit").status_code == 200
    for t in threads:
        t.join()
    for i in range(3):
        answers = more[i]
        assert [a["frame"] for a in answers] == list(range(len(drives[i + 1]),
                                                          len(drives[i + 1]) + len(extra[i])))
    metrics = c.get("/metrics").text
    assert 'sprint_map_commits_total{result="ok"} 1' in metrics
    frames = sum(len(d) for d in drives) + sum(len(e) for e in extra)
    answered = sum(float(line.split()[-1]) for line in metrics.splitlines()
                   if line.startswith("sprint_map_frames_total{"))
    assert answered == frames
    assert "sprint_map_sessions_active 3" in metrics
    assert f"sprint_map_frame_seconds_count{{payload=\"descriptor\"}} {frames}" in metrics


def test_bad_input_answers_clear_4xx(one_drive_map, start_server):
    server = start_server(one_drive_map, {"max_request_bytes": 16384,
                                          "max_frames_per_session": 3})
    c = server.client
    sid = c.post("/v1/sessions").json()["session_id"]
    frames = f"/v1/sessions/{sid}/frames"
    json_type = {"content-type": "application/json"}
    cases = [
        (c.post(frames, json={"descriptor": [0.5] * (DIM - 1)}), 422, "descriptor_shape"),
        (c.post(frames, content=json.dumps({"descriptor": [0.5] * (DIM - 1) + [float("nan")]}),
                headers=json_type), 422, "invalid_descriptor"),
        (c.post(frames, content="[1e999" + ", 1" * (DIM - 1) + "]", headers=json_type), 422,
         "bad_payload"),
        (c.post(frames, json={"descriptor": [1e39] * DIM}), 422, "invalid_descriptor"),
        (c.post(frames, json={"descriptor": [10**400] * DIM}), 422, "invalid_descriptor"),
        (c.post(frames, json={"descriptor": ["a"] * DIM}), 422, "bad_payload"),
        (c.post(frames, json={"descriptor": [True] * DIM}), 422, "bad_payload"),
        (c.post(frames, json={"descriptor": [0.1] * DIM, "x": 1}), 422, "bad_payload"),
        (c.post(frames, json=[0.1] * DIM), 422, "bad_payload"),
        (c.post(frames, content=b"{not json", headers=json_type), 400, "bad_json"),
        (c.post(frames, content=b"\xff\xfe", headers=json_type), 400, "bad_json"),
        (c.post(frames, content=b"\x89PNG...", headers={"content-type": "image/png"}), 415,
         "images_not_supported"),
        (c.post(frames, content=b"1,2", headers={"content-type": "text/csv"}), 415,
         "unsupported_media_type"),
        (c.post(frames, content=b"x" * 20000, headers=json_type), 413, "too_large"),
        (c.post("/v1/sessions/nope/frames", json={"descriptor": [0.1] * DIM}), 404,
         "unknown_session"),
        (c.post("/v1/sessions/nope/commit"), 404, "unknown_session"),
        (c.delete("/v1/sessions/nope"), 404, "unknown_session"),
        (c.post(f"/v1/sessions/{sid}/commit"), 409, "empty_session"),
        (c.post("/v1/sessions", json={"name": "first"}), 409, "duplicate_name"),
        (c.post("/v1/sessions", json={"name": "a\nb"}), 422, "bad_input"),
        (c.post("/v1/sessions", json={"name": 5}), 422, "bad_payload"),
        (c.post("/v1/sessions", content=b"{", headers=json_type), 400, "bad_json"),
        (c.get("/v1/nothing"), 404, "not_found"),
        (c.put("/v1/map"), 405, "method_not_allowed"),
    ]
    for i, (response, status, code) in enumerate(cases):
        assert (response.status_code, response.json().get("error")) == (status, code), (
            i, response.text)
        assert response.json()["message"]
    good = [0.1] * DIM
    first = c.post(frames, json={"descriptor": good})  # no position: then none, ever
    assert first.status_code == 200 and first.json()["frame"] == 0
    for body in ({"descriptor": good, "position": [1.0, 2.0]},
                 {"descriptor": good, "position": [1.0]},
                 {"descriptor": good, "position": [1.0, "a"]},
                 {"descriptor": good, "position": [1.0, 10**400]}):
        refused = c.post(frames, json=body)
        assert (refused.status_code, refused.json()["error"]) == (422, "bad_payload"), body
    # Nothing bad was kept: the session has its one good frame; the frame limit then holds.
    for _ in range(2):
        assert post_frame(c, sid, np.full(DIM, 0.1, np.float32)).status_code == 200
    limited = post_frame(c, sid, np.full(DIM, 0.1, np.float32))
    assert (limited.status_code, limited.json()["error"]) == (409, "frame_limit")
    named = c.post("/v1/sessions", json={"name": "same"}).json()["session_id"]
    assert c.post("/v1/sessions", json={"name": "same"}).status_code == 409  # open session
    deleted = c.delete(f"/v1/sessions/{named}").json()
    assert deleted == {"session_id": named, "frames": 0, "discarded": True}
    assert c.post("/v1/sessions", json={"name": "same"}).status_code == 201
    assert "sprint_map_http_requests_total" in c.get("/metrics").text
    assert server.terminate() == 0
    assert "Traceback" not in server.stderr()


def test_sigterm_commits_open_sessions_when_configured(one_drive_map, places, rng,
                                                       start_server):
    server = start_server(one_drive_map, {"on_shutdown": "commit"})
    c = server.client
    rows = drive(places, rng)
    kept = c.post("/v1/sessions", json={"name": "kept"}).json()["session_id"]
    stream(c, kept, rows[:30])
    c.post("/v1/sessions", json={"name": "empty"})
    server.proc.send_signal(signal.SIGTERM)
    assert server.proc.wait(60) == 0, server.stderr()
    server.close()
    with SprintMap.open(one_drive_map, readonly=True) as m:
        names = [s.name for s in m.sequences()]
        assert names == ["first", "kept"]  # the empty session had nothing to commit
        assert m.descriptors(1).tobytes() == rows[:30].tobytes()
        assert m.info()["index"]["persisted"] == m.stats()["vertices"]
        assert m.check().ok


def test_a_novel_admission_map_commits_what_it_lacks(places, rng, start_server, tmp_path):
    from sprint_map import MapConfig

    path = tmp_path / "fleet.map"
    first = drive(places, rng)
    with SprintMap.create(path, MapConfig(dim=DIM).replace(admission={"mode": "novel"})) as m:
        m.ingest(first, name="first")
    server = start_server(path)
    c = server.client
    sid = c.post("/v1/sessions", json={"name": "again"}).json()["session_id"]
    stream(c, sid, first)  # the very drive again: the map holds all of it
    committed = c.post(f"/v1/sessions/{sid}/commit").json()
    assert committed["seq_id"] is None and committed["name"] == "again"
    assert (committed["frames"], committed["frames_stored"]) == (len(first), 0)
    assert committed["frames_skipped"] == len(first) and committed["edges_added"] == 0
    assert server.terminate() == 0
    with SprintMap.open(path, readonly=True) as m:
        assert m.stats()["sequences"] == 1 and m.check().ok
        assert m.store.sighting(0, 5).count == 1
