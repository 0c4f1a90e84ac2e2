"""The viewer's routes, through the view app and mounted in serve behind its token."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from sprint_map.localize.trace import TraceRecorder, read_trace
from sprint_map.map import SprintMap
from sprint_map.viewer.app import create_view_app, mount_viewer
from sprint_map.viewer.overview import MapOverview

pytestmark = pytest.mark.road_map(drives=3, frames=80, with_thumbnails=True)


@pytest.fixture
def built(tmp_path, rng, road_map):
    query, _ = road_map.road.drive(rng, 60, start=3)
    with SprintMap.open(road_map.path, readonly=True) as m:
        loc = m.localizer()
        rec = TraceRecorder(m)
        rec.attach(loc)
        loc.localize(query)
        rec.save(tmp_path / "t.npz")
    return tmp_path / "m", tmp_path / "t.npz"


def test_the_page_and_its_api(built):
    path, trace = built
    with SprintMap.open(path, readonly=True) as m:
        client = TestClient(create_view_app(MapOverview(m), read_trace(trace)))
        page = client.get("/")
        assert page.status_code == 200 and "<canvas" in page.text
        assert "sprintViewer" in page.text and "http" not in page.text.split("<body>")[1]
        assert client.get("/viewer/api/overview").json()["counts"]["sequences"] == 4
        assert client.get("/viewer/api/sequences/1").json()["matched"]
        assert client.get("/viewer/api/sequences/77").status_code == 404
        assert client.get("/viewer/api/matrix/1/0?size=16").json()["rows"][-1] == 79
        assert client.get("/viewer/api/matrix/1/0?size=1").status_code == 422
        timeline = client.get("/viewer/api/trace").json()
        assert timeline["frames"] == 60 and len(timeline["dec_prob"]) == 60
        frames = client.get("/viewer/api/trace/frames?start=58&count=10").json()["frames"]
        assert [f["frame"] for f in frames] == [58, 59]
        assert len(frames[0]["top"]["xy"]) == len(frames[0]["top"]["seq"]) > 0
        assert client.get("/viewer/api/sequences/1").json()["thumbnails"] == 80
        jpeg = client.get("/viewer/api/thumbnails/1/7")
        assert jpeg.headers["content-type"] == "image/jpeg"
        assert jpeg.content == m.thumbnail(1, 7)
        assert client.get("/viewer/api/thumbnails/1/80").status_code == 404
        assert client.get("/viewer/api/thumbnails/9/0").status_code == 404


def test_without_a_trace_its_routes_answer_404(built):
    path, _ = built
    with SprintMap.open(path, readonly=True) as m:
        client = TestClient(create_view_app(MapOverview(m)))
        assert client.get("/viewer/api/trace").status_code == 404


def test_a_token_guards_the_api_not_the_page(built):
    path, _ = built
    with SprintMap.open(path, readonly=True) as m:
        client = TestClient(create_view_app(MapOverview(m), token="s3cret"))
        assert client.get("/").status_code == 200
        assert client.get("/viewer/api/overview").status_code == 401
        ok = client.get("/viewer/api/overview", headers={"Authorization": "Bearer s3cret"})
        assert ok.status_code == 200


def test_serve_shows_the_page_at_root_behind_its_token(built, monkeypatch):
    from sprint_map.server.app import create_app
    from sprint_map.server.config import ServerConfig
    from sprint_map.server.service import LocalisationService

    path, _ = built
    service = LocalisationService(SprintMap.open(path), ServerConfig())
    with TestClient(create_app(service, token="s3cret", extensions=[mount_viewer])) as client:
        assert client.get("/").status_code == 200
        assert client.get("/viewer/api/overview").status_code == 401
        auth = {"Authorization": "Bearer s3cret"}
        ov = client.get("/viewer/api/overview", headers=auth).json()
        assert ov["counts"]["sequences"] == 4
        assert client.get("/viewer/api/matrix/1/0", headers=auth).status_code == 200
        assert client.get("/viewer/api/trace", headers=auth).status_code == 404
        assert not any(p.startswith("/viewer") for p in client.get("/openapi.json").json()["paths"])
    np.testing.assert_equal(service.map.store.env, None)  # the lifespan closed the map
