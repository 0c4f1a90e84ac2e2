"""A tokenless ``serve`` cannot be driven by a web page (issue 29 item 7): the Host header
must name the server, a write must carry JSON, the binary or an image content type."""

from __future__ import annotations

import httpx


def test_host_names():
    from sprint_map.server.guard import host_name

    assert host_name("127.0.0.1:8000") == "127.0.0.1"
    assert host_name("[::1]:80") == "[::1]" and host_name("LocalHost") == "localhost"


def test_tokenless_serve_refuses_what_a_page_could_send(start_server, one_drive_map):
    """Was: a cross-origin text/plain POST with no body made a session (201) every time
    (300 filled the 256 sessions) and any Host was answered."""
    server = start_server(one_drive_map, {"max_sessions": 4})
    url = server.url
    for _ in range(8):  # blind cross-origin posts: none makes a session
        refused = httpx.post(url + "/v1/sessions", headers={
            "content-type": "text/plain", "origin": "http://evil.example"}, timeout=30)
        assert refused.status_code == 415, refused.text
        assert httpx.post(url + "/v1/sessions", headers={"origin": "http://evil.example"},
                          timeout=30).status_code == 415
        assert httpx.post(url + "/v1/sessions", content=b"name=x", headers={
            "content-type": "application/x-www-form-urlencoded"}, timeout=30).status_code == 415
    rebound = httpx.post(url + "/v1/sessions", json={}, headers={"host": "evil.example"},
                         timeout=30)
    assert rebound.status_code == 403 and rebound.json()["error"] == "host"
    assert httpx.get(url + "/v1/map", headers={"host": "evil.example:80"},
                     timeout=30).status_code == 403
    # vehicles and tools: JSON, or an empty body without a content type (not a browser)
    assert httpx.post(url + "/v1/sessions", json={"name": "a"}, timeout=30).status_code == 201
    sid = httpx.post(url + "/v1/sessions", timeout=30).json()["session_id"]
    assert httpx.delete(f"{url}/v1/sessions/{sid}", timeout=30).status_code == 200
    assert httpx.get(url + "/healthz", timeout=30).status_code == 200


def test_configured_names_are_answered(start_server, one_drive_map):
    server = start_server(one_drive_map, {"allowed_hosts": ["mapbox.local"]})
    assert httpx.get(server.url + "/v1/map", headers={"host": "mapbox.local:1234"},
                     timeout=30).status_code == 200


def test_with_a_token_any_host_and_type_reach_the_token_check(start_server, one_drive_map):
    server = start_server(one_drive_map, env={"SPRINT_MAP_TOKEN": "s3cret"})
    answer = httpx.post(server.url + "/v1/sessions", headers={
        "host": "mapbox.example", "content-type": "text/plain",
        "authorization": "Bearer s3cret"}, timeout=30)
    assert answer.status_code == 201
