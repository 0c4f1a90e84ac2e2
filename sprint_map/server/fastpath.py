"""FrameFastPath: ``POST /v1/sessions/{id}/frames`` answered without FastAPI's request cycle.

A frame is the one request a fleet sends hundreds of times a second, and on 2 cores the
framework's per-request work (routing, dependency injection, the ``Request`` object, response
model validation, its middleware layers) cost more than the batched search of the frame. This
ASGI middleware answers exactly that route, with the same service call, the same answer (the
:class:`~sprint_map.server.app.FrameAnswer` fields), the same error bodies and statuses; every
other request (and any other method on that path) goes to the FastAPI app, which still
documents the route in the schema.

It sits inside :class:`~sprint_map.server.app.RequestGuard` (the token has been checked and the
body read, bounded in size and time, before it runs) and :class:`~sprint_map.server.app.
RequestMetrics` (it names the route template in the scope, so requests are counted under
it). An error other than an :class:`~sprint_map.server.errors.ApiError` propagates to the
server's error middleware, as from a route.
"""

from __future__ import annotations

import json
import re
from typing import Any

from starlette.types import ASGIApp, Message, Receive, Scope, Send

from sprint_map.server.errors import ApiError
from sprint_map.server.service import LocalisationService

__all__ = ["FRAME_PATH", "FrameFastPath", "frame_answer"]

#: The route (a contract) and the pattern of its paths.
FRAME_PATH = "/v1/sessions/{session_id}/frames"
_FRAME_RE = re.compile(r"^/v1/sessions/([^/]+)/frames$")
#: The fields of a frame's answer (``FrameAnswer`` in the schema).
_FIELDS = ("frame", "seq_id", "image_id", "prob", "timing")


def frame_answer(out: dict[str, Any]) -> dict[str, Any]:
    """The service's answer restricted to the documented fields, as the route answers it."""
    return {key: out[key] for key in _FIELDS}


def _json(data: Any) -> bytes:
    """JSON as :class:`~sprint_map.server.app.SafeJSONResponse` renders it."""
    return json.dumps(data, ensure_ascii=False, allow_nan=False, indent=None,
                      separators=(",", ":")).encode("utf-8", "backslashreplace")


class FrameFastPath:
    """ASGI middleware answering ``POST`` frames directly (see the module docstring).

    Parameters
    ----------
    app : ASGIApp
        The application for every other request.
    service : LocalisationService
        The service whose :meth:`~LocalisationService.frame` answers.
    route : object, optional
        The app's route object for :data:`FRAME_PATH`, put in the scope for the metrics.
    """

    def __init__(self, app: ASGIApp, service: LocalisationService, route: Any = None) -> None:
        self.app = app
        self.service = service
        self.route = route

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        match = (_FRAME_RE.match(scope.get("path", "")) if scope["type"] == "http"
                 and scope.get("method") == "POST" else None)
        if match is None:
            await self.app(scope, receive, send)
            return
        if self.route is not None:
            scope["route"] = self.route
        chunks = []
        while True:  # the guard has buffered the body: one message
            message = await receive()
            if message["type"] != "http.request":
                return  # the client went away
            chunks.append(message.get("body", b""))
            if not message.get("more_body", False):
                break
        content_type = None
        for name, value in scope.get("headers") or ():
            if name == b"content-type":
                content_type = value.decode("latin-1")
        try:
            out = await self.service.frame(match.group(1), content_type, b"".join(chunks))
        except ApiError as err:
            await _respond(send, err.status, err.body(), err.headers)
            return
        await _respond(send, 200, frame_answer(out))


async def _respond(send: Send, status: int, data: Any, headers: dict[str, str] | None = None
                   ) -> None:
    body = _json(data)
    raw = [(b"content-type", b"application/json"),
           (b"content-length", str(len(body)).encode())]
    raw += [(k.lower().encode("latin-1"), v.encode("latin-1")) for k, v in (headers or {}).items()]
    start: Message = {"type": "http.response.start", "status": status, "headers": raw}
    await send(start)
    await send({"type": "http.response.body", "body": body})
