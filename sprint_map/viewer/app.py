"""The viewer's HTTP routes: one page at ``/`` and its JSON under ``/viewer/api/``.

The same router serves ``sprint-map view`` (its own app, :func:`create_view_app`) and
``sprint-map serve`` (mounted into the service's app, behind its token). The page is one
self-contained HTML document (its script and style inlined from the package's ``static``
folder, no CDN): it holds no map data, so it is answered without the token; every route that
reads the map requires it (the page asks for it and sends it as a bearer header).

Routes (a contract for the page):

``GET /``                                    the page
``GET /viewer/api/overview``                 :meth:`MapOverview.overview`
``GET /viewer/api/sequences/{seq}``          :func:`drive_detail`
``GET /viewer/api/matrix/{seq}/{other}``     :func:`match_matrix` (``?size=`` up to 512)
``GET /viewer/api/trace``                    :func:`playback.timeline` (404 without a trace)
``GET /viewer/api/trace/frames``             :func:`playback.frames` (``?start=&count=``)
``GET /viewer/api/thumbnails/{seq}/{image}`` the frame's JPEG, when the map keeps thumbnails
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Coroutine, Sequence
from importlib import resources
from typing import TYPE_CHECKING, Any

from fastapi import APIRouter, FastAPI, HTTPException, Query, Request
from fastapi.params import Depends
from fastapi.responses import HTMLResponse, JSONResponse, Response
from fastapi.routing import APIRoute

from sprint_map import Trace
from sprint_map.errors import UnknownSequenceError
from sprint_map.viewer import playback
from sprint_map.viewer.matrix import MATRIX_SIZE, drive_detail, match_matrix
from sprint_map.viewer.overview import MapOverview

if TYPE_CHECKING:
    from sprint_map.server.config import ServerConfig
    from sprint_map.server.service import LocalisationService

__all__ = ["API_PREFIX", "create_view_app", "mount_viewer", "page_html", "viewer_router"]

API_PREFIX = "/viewer/api"


@functools.cache
def page_html() -> str:
    """The page: ``index.html`` with ``viewer.css`` and ``viewer.js`` inlined (read once)."""
    static = resources.files("sprint_map.viewer") / "static"
    html = (static / "index.html").read_text("utf-8")
    css = (static / "viewer.css").read_text("utf-8")
    js = (static / "viewer.js").read_text("utf-8")
    return (html.replace("/*{{viewer.css}}*/", css)
            .replace("/*{{viewer.js}}*/", js.replace("</script", "<\\/script")))


def viewer_router(summary: MapOverview, trace: Trace | None = None,
                  dependencies: Sequence[Depends] = ()) -> APIRouter:
    """The page and its API over ``summary`` (and ``trace``, if one is shown).

    ``dependencies`` guard the API routes (the service's token check); the page is public.
    The routes are plain functions: FastAPI runs them in its thread pool, off the event loop.
    """
    router = APIRouter(route_class=_KnownDrivesRoute)
    # not in the OpenAPI schema: the page's own API, documented in docs/viewer.md
    api = APIRouter(prefix=API_PREFIX, dependencies=list(dependencies), include_in_schema=False,
                    route_class=_KnownDrivesRoute)

    @router.get("/", response_class=HTMLResponse, include_in_schema=False)
    def page() -> HTMLResponse:
        return HTMLResponse(page_html(), headers={"Cache-Control": "no-cache"})

    @api.get("/overview", summary="Viewer: the map's overview (level of detail)")
    def overview() -> dict[str, Any]:
        return summary.overview() | {"trace": trace is not None}  # a shallow copy

    @api.get("/sequences/{seq_id}", summary="Viewer: a drive and the drives it matched")
    def sequence(seq_id: int) -> dict[str, Any]:
        detail = drive_detail(summary, seq_id)
        if detail is None:
            raise HTTPException(404, f"no sequence {seq_id} in the map")
        detail["thumbnails"] = _thumbnail_count(summary, seq_id)
        return detail

    @api.get("/matrix/{seq_id}/{other}", summary="Viewer: similarity matrix of two drives")
    def matrix(seq_id: int, other: int,
               size: int = Query(MATRIX_SIZE, ge=2, le=512)) -> dict[str, Any]:
        try:
            return match_matrix(summary, seq_id, other, size)
        except KeyError as exc:
            raise HTTPException(404, f"no sequence {exc.args[0]} in the map") from exc

    @api.get("/trace", summary="Viewer: the trace's timeline")
    def trace_timeline() -> dict[str, Any]:
        return playback.timeline(_need(trace))

    @api.get("/trace/frames", summary="Viewer: a page of the trace's frames")
    def trace_frames(start: int = Query(0, ge=0),
                     count: int = Query(100, ge=1, le=playback.PAGE)) -> dict[str, Any]:
        shown = _need(trace)
        return {"start": start,
                "frames": playback.frames(shown, summary, start, count)}

    @api.get("/thumbnails/{seq_id}/{image_id}", summary="Viewer: a frame's JPEG thumbnail",
             response_class=Response)
    def thumbnail(seq_id: int, image_id: int) -> Response:
        data = _thumbnail(summary, seq_id, image_id)
        if data is None:
            raise HTTPException(404, f"no thumbnail of image {image_id} of sequence {seq_id}")
        return Response(data, media_type="image/jpeg",
                        headers={"Cache-Control": "private, max-age=3600"})

    router.include_router(api)
    return router


class _KnownDrivesRoute(APIRoute):
    """A route whose ``UnknownSequenceError`` (a drive removed by another process while the
    request read it) is a 404, never a 500."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def handle(request: Request) -> Response:
            try:
                return await handler(request)
            except UnknownSequenceError as exc:
                return JSONResponse({"detail": str(exc)}, status_code=404)

        return handle


def _need(trace: Trace | None) -> Trace:
    if trace is None:
        raise HTTPException(404, "no trace shown (sprint-map view MAP --trace OUT)")
    return trace


def _thumbnail_count(summary: MapOverview, seq_id: int) -> int:
    """How many thumbnails the drive keeps (0: ingested without ``--thumbnails``)."""
    return int(summary.read(lambda: summary.map.thumbnail_count(seq_id)))


def _thumbnail(summary: MapOverview, seq_id: int, image_id: int) -> bytes | None:
    try:
        data = summary.read(lambda: summary.map.thumbnail(seq_id, image_id))
    except UnknownSequenceError:
        return None
    return None if data is None else bytes(data)


def mount_viewer(app: FastAPI, service: LocalisationService, guard: list[Any]) -> None:
    """The viewer's page at ``/`` of the localisation service and its API behind ``guard``
    (each read under the service's map gate): an extension of
    :func:`sprint_map.server.app.create_app`, as ``sprint-map serve`` mounts it."""

    def shared(fn: Any) -> Any:
        with service.gate.shared():
            return fn()

    app.include_router(viewer_router(MapOverview(service.map, shared), None, guard))


def create_view_app(summary: MapOverview, trace: Trace | None = None,
                    token: str | None = None, config: ServerConfig | None = None) -> FastAPI:
    """The app of ``sprint-map view``: the page and its API (with ``token``: API routes need
    ``Authorization: Bearer <token>``, as in ``serve``, checked by ``serve``'s
    :class:`~sprint_map.server.app.RequestGuard` before any body byte is read)."""
    from sprint_map.server.app import RequestGuard
    from sprint_map.server.auth import token_matches
    from sprint_map.server.config import ServerConfig

    config = config or ServerConfig()

    async def authorised(request: Request) -> None:
        if token is not None and not token_matches(request.headers.get("authorization"), token):
            raise HTTPException(401, "missing or wrong bearer token",
                                headers={"WWW-Authenticate": "Bearer"})

    app = FastAPI(title="sprint-map viewer", docs_url=None, redoc_url=None)
    app.include_router(viewer_router(summary, trace, [Depends(authorised)]))
    app.add_middleware(RequestGuard, limit=config.max_request_bytes, token=token,
                       body_timeout_s=config.body_timeout_s)
    return app
