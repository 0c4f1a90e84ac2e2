"""The HTTP API (FastAPI on uvicorn): routes, error answers, the token and body limits.

Paths (a contract): ``POST /v1/sessions``, ``POST /v1/sessions/{id}/frames``,
``POST /v1/sessions/{id}/commit``, ``DELETE /v1/sessions/{id}``, ``GET /v1/map``,
``GET /healthz``, ``GET /readyz``, ``GET /metrics``; the schema is at ``/openapi.json``.
"""

from __future__ import annotations

import json
from collections.abc import AsyncIterator, Callable, Sequence
from contextlib import asynccontextmanager
from typing import Annotated, Any

import anyio
from fastapi import Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, PlainTextResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import BaseModel, ConfigDict, Field
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from sprint_map import MAX_LAG
from sprint_map.server.auth import token_matches
from sprint_map.server.errors import ApiError
from sprint_map.server.fastpath import FRAME_PATH, FrameFastPath
from sprint_map.server.metrics import Metrics
from sprint_map.server.service import LocalisationService

__all__ = ["AppExtension", "BEARER", "CommitAnswer", "Discarded", "Error", "FrameAnswer",
           "FrameTiming", "LaggedAnswer", "PUBLIC_PATHS", "RequestGuard", "RequestMetrics", "SafeJSONResponse",
           "SessionCreate", "SessionCreated", "Status", "create_app", "frame_body"]

# --- schemas (documentation of the contract) ---------------------------------------------------
class Error(BaseModel):
    error: str = Field(description="Stable machine-readable code, e.g. descriptor_shape.")
    message: str


class SessionCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str | None = Field(None, description="Sequence name for the commit (unique in the map).")
    lag: int = Field(0, ge=0, le=MAX_LAG, strict=True,
                     description="Answer each frame once this many more were posted (fixed-lag "
                                 "smoothing; 0: causal, at once). A frame's answer then names "
                                 "the frame it answers; the commit answers the last ones.")


class JoinRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")
    source: str = Field(description="Path of the map to join, on the server's file system "
                                    "(opened read-only).")
    drives: list[str] | None = Field(None, description="Only these drives (default: all).")
    prefix: str = Field("", description="Prepended to every imported drive's name.")
    merge: bool = Field(True, description="Localise and merge the drives (false: only copy).")
    require_connected: bool = Field(False, description="Refuse a join that leaves an imported "
                                                       "drive unconnected.")


class SessionCreated(BaseModel):
    session_id: str


class FrameTiming(BaseModel):
    retrieval_ms: float
    hmm_ms: float
    server_ms: float = Field(description="Admission to answer in the server, queueing included.")


class FrameAnswer(BaseModel):
    frame: int | None = Field(description="Index in its session (0, 1, ...) of the frame "
                              "answered: the one posted, or with a lag L the one posted L "
                              "frames before (null, and every field but timing, while fewer "
                              "than L + 1 frames were posted).")
    seq_id: int | None = Field(description="Matched sequence; null for no match.")
    image_id: int | None = Field(description="Matched image of that sequence; null for no match.")
    prob: float | None = Field(description="Posterior mass of the decided (or best) place.")
    timing: FrameTiming


class LaggedAnswer(BaseModel):
    frame: int
    seq_id: int | None
    image_id: int | None
    prob: float


class CommitAnswer(BaseModel):
    seq_id: int | None = Field(description="The new sequence; null when the map's admission "
                                           "stored no frame of the drive.")
    name: str
    frames: int
    frames_stored: int
    frames_skipped: int
    edges_added: int
    component: int | None
    decisions: list[LaggedAnswer] | None = Field(
        None, description="A session with a lag: the answers of its last frames (those not "
                          "answered yet), in frame order; absent otherwise.")


class Discarded(BaseModel):
    session_id: str
    frames: int
    discarded: bool


class Status(BaseModel):
    status: str


_ERRORS: dict[int | str, dict[str, Any]] = {
    code: {"model": Error, "description": text} for code, text in (
        (400, "The body is not valid JSON."),
        (401, "Missing or wrong bearer token."),
        (404, "Unknown session."),
        (409, "Conflict with the session's state or the map (e.g. duplicate name, empty)."),
        (413, "Request body too large."),
        (415, "Unsupported content type."),
        (422, "Invalid payload (dimension, NaN/Inf, undecodable image, bad field)."),
        (429, "Too many frames of this session waiting."),
        (503, "A bounded queue or limit is full, or the server is shutting down."),
    )
}

def frame_body(dim: int) -> dict[str, Any]:
    """The frame route's request body in the schema (two media types; ``dim`` values)."""
    descriptor = {"type": "object", "additionalProperties": False, "required": ["descriptor"],
                  "properties": {"descriptor": {"type": "array",
                                                "items": {"type": "number", "minimum": -3e38,
                                                          "maximum": 3e38},
                                                "minItems": dim, "maxItems": dim},
                                 "position": {"type": "array", "minItems": 2, "maxItems": 3,
                                              "items": {"type": "number", "minimum": -1e12,
                                                        "maximum": 1e12},
                                              "description": "Optional [x, y(, heading_deg)] "
                                              "of the frame: for every frame or none."}}}
    binary = {"schema": {"type": "string", "format": "binary"}}
    return {
        "requestBody": {
            "required": True,
            "description": f'JSON {{"descriptor": [{dim} floats]}}, or the same as {4 * dim} '
                           "bytes of little-endian float32 (application/octet-stream, no JSON "
                           "parsing), or the encoded image (PNG, JPEG, ...) with an image/* "
                           "content type; images need a map of hog or patchnorm descriptors.",
            "content": {"application/json": {"schema": descriptor},
                        "application/octet-stream": {"schema": {
                            "type": "string", "format": "binary", "minLength": 4 * dim,
                            "maxLength": 4 * dim,
                            "description": f"{dim} little-endian float32 values"}},
                        "image/png": binary, "image/jpeg": binary},
        }
    }


#: Documents the optional bearer token in the schema; checked by ``RequestGuard`` (before the
#: body is read) and again by ``authorised``.
BEARER = HTTPBearer(auto_error=False, description="Required when the server has a token.")


#: Paths answered without the token (liveness, readiness, the API's documentation, the viewer's
#: page, which holds no map data: its /viewer/api/ requests carry the token).
PUBLIC_PATHS = frozenset({"/", "/healthz", "/readyz", "/openapi.json", "/docs",
                          "/docs/oauth2-redirect", "/redoc"})


class RequestGuard:
    """ASGI middleware: the token, then the body's size and time, before the app runs.

    In this order, from the headers alone: a request to a guarded path without the right
    bearer token is answered 401 before a byte of its body is read (the routes' ``authorised``
    dependency then documents the scheme and checks again); a ``Content-Length`` above
    ``limit`` is answered 413. Then the body is buffered up to ``limit`` bytes (413 beyond),
    all of it within ``body_timeout_s`` (408 otherwise), so no route reads more or waits longer.
    An answer given before the body was read closes the connection.
    """

    def __init__(self, app: ASGIApp, limit: int, token: str | None = None,
                 body_timeout_s: float = 30.0) -> None:
        self.app = app
        self.limit = limit
        self.token = token
        self.body_timeout_s = body_timeout_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers") or [])
        if (self.token is not None and scope.get("path") not in PUBLIC_PATHS
                and not token_matches(_latin1(headers.get(b"authorization")), self.token)):
            await _refuse(send, ApiError(401, "unauthorised", "missing or wrong bearer token",
                                         {"WWW-Authenticate": "Bearer"}))
            return
        length = headers.get(b"content-length")
        if length is not None and (not length.isdigit() or int(length) > self.limit):
            await _refuse(send, self._too_large())
            return
        chunks: list[bytes] = []
        size = 0
        try:
            with anyio.fail_after(self.body_timeout_s):
                while True:
                    message = await receive()
                    if message["type"] != "http.request":
                        break  # a disconnect: the app sees it below
                    chunk = message.get("body", b"")
                    size += len(chunk)
                    if size > self.limit:
                        await _refuse(send, self._too_large())
                        return
                    chunks.append(chunk)
                    if not message.get("more_body", False):
                        break
        except TimeoutError:
            await _refuse(send, ApiError(408, "timeout", "the request body did not arrive "
                                         f"within {self.body_timeout_s:g} s"))
            return
        body = b"".join(chunks)
        sent = False

        async def replay() -> Message:
            nonlocal sent
            if not sent:
                sent = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)

    def _too_large(self) -> ApiError:
        return ApiError(413, "too_large", f"request body exceeds {self.limit} bytes")


def _latin1(value: bytes | None) -> str | None:
    return None if value is None else value.decode("latin-1")


async def _refuse(send: Send, err: ApiError) -> None:
    """Answer ``err`` and close the connection (its body, if any, is not read)."""
    response = SafeJSONResponse(err.body(), status_code=err.status,
                                headers={**err.headers, "Connection": "close"})
    await response({"type": "http"}, _no_receive, send)


class RequestMetrics:
    """ASGI middleware: count requests by method, route template and status."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app = app
        self.metrics = metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        status = 500

        async def send_status(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_status)
        finally:
            route = getattr(scope.get("route"), "path", "other")
            self.metrics.requests.inc(method=scope.get("method", ""), route=route,
                                      status=str(status))


class SafeJSONResponse(JSONResponse):
    """JSON whose text is always UTF-8: a lone surrogate (valid in a JSON string, not text)
    echoed from a request is written as its ``\\uXXXX`` escape, not a 500."""

    def render(self, content: Any) -> bytes:
        return json.dumps(content, ensure_ascii=False, allow_nan=False, indent=None,
                          separators=(",", ":")).encode("utf-8", "backslashreplace")


async def _no_receive() -> Message:
    return {"type": "http.disconnect"}


#: Adds routes to the service's app: ``extension(app, service, guard)``; ``guard`` is the
#: dependency list that checks the bearer token (e.g. :func:`sprint_map.viewer.app.mount_viewer`).
AppExtension = Callable[[FastAPI, LocalisationService, list[Any]], None]


def create_app(service: LocalisationService, token: str | None = None,
               extensions: Sequence[AppExtension] = ()) -> FastAPI:
    """The FastAPI app over ``service``; its lifespan starts and shuts the service down.

    ``extensions`` add their routes after the service's (``sprint-map serve`` adds the
    viewer's page at ``/``).
    """

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        await service.start()
        try:
            yield
        finally:
            await service.shutdown()

    app = FastAPI(
        title="sprint-map localisation service",
        version="1",
        summary="Vehicles stream frames, the map answers with places and grows with each drive.",
        lifespan=lifespan,
        default_response_class=SafeJSONResponse,
    )
    async def authorised(
        request: Request, creds: Annotated[HTTPAuthorizationCredentials | None, Depends(BEARER)]
    ) -> None:
        if token is not None and not token_matches(request.headers.get("authorization"), token):
            raise ApiError(401, "unauthorised", "missing or wrong bearer token",
                           {"WWW-Authenticate": "Bearer"})

    guard = [Depends(authorised)]

    @app.exception_handler(ApiError)
    async def api_error(_: Request, exc: ApiError) -> JSONResponse:
        return SafeJSONResponse(exc.body(), status_code=exc.status, headers=exc.headers)

    @app.exception_handler(RequestValidationError)
    async def invalid(_: Request, exc: RequestValidationError) -> JSONResponse:
        first = exc.errors()[0] if exc.errors() else {}
        where = ".".join(str(p) for p in first.get("loc", ()))
        status = 400 if first.get("type") == "json_invalid" else 422
        code = "bad_json" if status == 400 else "bad_payload"
        return SafeJSONResponse({"error": code, "message": f"{where}: {first.get('msg', 'invalid')}"},
                            status_code=status)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(_: Request, exc: StarletteHTTPException) -> JSONResponse:
        code = {404: "not_found", 405: "method_not_allowed"}.get(exc.status_code, "http_error")
        return SafeJSONResponse({"error": code, "message": str(exc.detail)},
                            status_code=exc.status_code, headers=getattr(exc, "headers", None))

    @app.post("/v1/sessions", status_code=201, response_model=SessionCreated,
              responses=_ERRORS, dependencies=guard, summary="Start a drive")
    async def create_session(body: SessionCreate | None = None) -> dict[str, str]:
        session = await service.create_session(body.name if body else None,
                                               body.lag if body else 0)
        return {"session_id": session.id}

    @app.post("/v1/sessions/{session_id}/frames", response_model=FrameAnswer,
              responses=_ERRORS, dependencies=guard, openapi_extra=frame_body(service.dim),
              summary="Localise the next frame of a drive")
    async def frame(session_id: str, request: Request) -> dict[str, Any]:
        body = await request.body()
        return await service.frame(session_id, request.headers.get("content-type"), body)

    @app.post("/v1/sessions/{session_id}/commit", response_model=CommitAnswer,
              response_model_exclude_unset=True, responses=_ERRORS, dependencies=guard,
              summary="Merge the drive into the map (answered once durable)")
    async def commit(session_id: str) -> dict[str, Any]:
        return await service.commit(session_id)

    @app.delete("/v1/sessions/{session_id}", response_model=Discarded, responses=_ERRORS,
                dependencies=guard, summary="Discard a drive")
    async def discard(session_id: str) -> dict[str, Any]:
        session = await service.discard(session_id)
        return {"session_id": session.id, "frames": session.frames, "discarded": True}

    @app.post("/v1/joins", responses=_ERRORS, dependencies=guard,
              summary="Join another map's drives (through the writer; answered once durable)")
    async def join(body: JoinRequest) -> dict[str, Any]:
        return await service.join(body.source, body.model_dump(exclude={"source"}))

    @app.get("/v1/map", responses=_ERRORS, dependencies=guard,
             summary="The map's summary (the fields of sprint-map info --json)")
    async def map_info() -> dict[str, Any]:
        return await service.map_info()

    @app.get("/healthz", response_model=Status, summary="The process answers")
    async def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get("/readyz", response_model=Status, responses={503: {"model": Error}},
             summary="Ready to answer frames (map open, index loaded, writer running)")
    async def readyz() -> Any:
        if service.ready and service.writer.alive and not service.closing:
            return {"status": "ready"}
        return SafeJSONResponse({"error": "not_ready", "message": "starting or shutting down"},
                            status_code=503)

    @app.get("/metrics", response_class=PlainTextResponse, dependencies=guard,
             summary="Prometheus metrics (text format 0.0.4)")
    async def metrics() -> PlainTextResponse:
        text = await anyio.to_thread.run_sync(service.metrics.render)
        return PlainTextResponse(text, media_type="text/plain; version=0.0.4")

    for extend in extensions:
        extend(app, service, guard)
    # Frames skip FastAPI's request cycle (server/fastpath.py); inside the guard and metrics.
    app.add_middleware(FrameFastPath, service=service, route=next(
        r for r in app.routes if getattr(r, "path", None) == FRAME_PATH))
    app.add_middleware(RequestGuard, limit=service.config.max_request_bytes, token=token,
                       body_timeout_s=service.config.body_timeout_s)
    app.add_middleware(RequestMetrics, metrics=service.metrics)
    return app
