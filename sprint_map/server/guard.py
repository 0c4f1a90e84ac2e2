"""Connection-level limits uvicorn's httptools protocol lacks: the service cannot be starved.

uvicorn 0.5x with httptools (what ``serve`` runs) enforces none of what a server facing
untrusted clients needs before a request reaches the app: no timeout while a request's headers
arrive (only ``timeout_keep_alive`` between requests), no header size limit
(``h11_max_incomplete_event_size`` applies to the h11 protocol only; httptools appends a header
line chunk by chunk, unbounded), and ``limit_concurrency`` counts every open connection, so 600
connections that sent half a header make every request, ``/healthz`` included, answer 503.

:func:`guarded_protocol` subclasses uvicorn's ``HttpToolsProtocol`` (a documented extension
point: ``uvicorn.Config(http=<class>)``) with:

- a **header deadline**: a connection's request headers must be complete within
  ``header_timeout_s`` of its opening (or of the end of its previous response); otherwise it is
  answered 408 and closed;
- a **header size limit**: more than ``max_header_bytes`` received before the headers end is
  answered 431 and closed (at most one read, 256 KiB, beyond the limit is ever held);
- a **connection limit that keeps the service answering**: beyond ``max_connections`` open
  connections, a new one closes the connection without a request in progress that is least
  worth keeping (one that never completed a request before one that did, then the longest
  quiet); connections with a request in progress are never closed. If every connection is busy,
  requests on the connections beyond the limit are answered 503 ``busy`` (JSON), except
  ``/healthz`` and ``/readyz``, which always answer; beyond twice the limit a new connection is
  closed at once.

Without a token (loopback only), two more checks stop a web page the user visits from driving
the server (CSRF, DNS rebinding), from the headers alone:

- the ``Host`` header must name the bound address, a loopback name or a configured name
  (``ServerConfig.allowed_hosts``); otherwise 403 ``host``;
- a write (POST, PUT, PATCH, DELETE) must say ``application/json``,
  ``application/octet-stream`` or ``image/*``; a form or ``text/plain`` (what a page may send
  cross-origin without asking) is 415, as is a write without a content type that a browser
  sent (it carries ``Origin`` or ``Sec-Fetch-Mode``; other clients may omit the type of an
  empty body).

Body limits and the token (checked before any body byte is read) are ASGI middleware
(:class:`sprint_map.server.app.RequestGuard`). Memory held by connections that have not
authenticated is then bounded by ``2 x max_connections x (max_header_bytes + 256 KiB)``
(uvicorn pauses reading a body at 64 KiB until the app asks for it, and the app answers 401
before asking).
"""

from __future__ import annotations

import asyncio
import heapq
import json
import logging
from dataclasses import dataclass
from typing import Any

import httptools
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

__all__ = ["ALWAYS_ANSWERED", "ConnectionLimits", "error_response", "guarded_protocol",
           "host_name"]

log = logging.getLogger("sprint_map.server")

#: Paths answered even when every connection is busy (they read nothing of the map).
ALWAYS_ANSWERED = frozenset({b"/healthz", b"/readyz"})


@dataclass(frozen=True)
class ConnectionLimits:
    """The limits :func:`guarded_protocol` enforces (from :class:`ServerConfig`)."""

    max_connections: int
    max_header_bytes: int
    header_timeout_s: float
    #: Host names a tokenless server answers (lower case, no port); None: no check (a token).
    hosts: frozenset[str] | None = None


def error_response(status: int, reason: str, code: str, message: str,
                   extra: tuple[tuple[str, str], ...] = ()) -> bytes:
    """A complete ``Connection: close`` HTTP/1.1 answer with the service's JSON error body."""
    body = json.dumps({"error": code, "message": message}, separators=(",", ":")).encode()
    head = [f"HTTP/1.1 {status} {reason}", "content-type: application/json",
            f"content-length: {len(body)}", "connection: close",
            *(f"{k}: {v}" for k, v in extra)]
    return ("\r\n".join(head) + "\r\n\r\n").encode() + body


def guarded_protocol(limits: ConnectionLimits) -> type[HttpToolsProtocol]:
    """uvicorn's httptools protocol class with ``limits`` enforced (see the module doc)."""

    class GuardedHttpToolsProtocol(_Guarded):
        pass

    GuardedHttpToolsProtocol.limits = limits
    return GuardedHttpToolsProtocol


class _Guarded(HttpToolsProtocol):
    limits: ConnectionLimits

    # --- connection lifecycle -----------------------------------------------------------------
    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._served = 0  # responses completed on this connection
        self._quiet_since = self.loop.time()
        self._header_bytes = 0
        self._in_headers = True
        self._header_timer: asyncio.TimerHandle | None = None
        self._arm_header_timer()
        self._make_room()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cancel_header_timer()
        super().connection_lost(exc)

    def _open_peers(self) -> list[_Guarded]:
        return [c for c in self.connections
                if isinstance(c, _Guarded) and not c.transport.is_closing()]

    def _busy(self) -> bool:
        """A request is in progress (headers complete, response not complete)."""
        return (self.cycle is not None and not self.cycle.response_complete) or bool(
            self.pipeline)

    def _make_room(self) -> None:
        """Keep at most ``max_connections`` open, closing the least useful idle ones."""
        if len(self.connections) <= self.limits.max_connections:
            return  # (the common case, without a scan)
        peers = self._open_peers()
        excess = len(peers) - self.limits.max_connections
        if excess <= 0:
            return
        idle = [c for c in peers if c is not self and not c._busy()]
        # Never served (a half-sent request, or nothing at all) before served; then oldest quiet.
        # A flood of new connections would scan the peers once each: close a slack of never
        # served ones beyond the excess too, so the next scans wait for that many new ones.
        slack = max(1, self.limits.max_connections // 16)
        ranked = heapq.nsmallest(excess + slack, idle,
                                 key=lambda c: (c._served > 0, c._quiet_since))
        for i, victim in enumerate(ranked):
            if i < excess or victim._served == 0:
                victim._close_quietly()
        if len(peers) - min(excess, len(idle)) > 2 * self.limits.max_connections:
            log.warning("connection refused: %d connections, all busy", len(peers))
            self.transport.close()

    def _close_quietly(self) -> None:
        self._cancel_header_timer()
        self.transport.close()

    # --- headers ------------------------------------------------------------------------------
    def _arm_header_timer(self) -> None:
        self._cancel_header_timer()
        self._header_timer = self.loop.call_later(self.limits.header_timeout_s,
                                                  self._header_timeout)

    def _cancel_header_timer(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _header_timeout(self) -> None:
        self._header_timer = None
        if self.transport.is_closing() or not self._in_headers or self._busy():
            return
        if self._header_bytes:
            self._refuse(408, "Request Timeout", "timeout", "the request's headers did not "
                         f"arrive within {self.limits.header_timeout_s:g} s")
        else:
            self.transport.close()  # nothing was asked: just close, as for keep-alive

    def _refuse(self, status: int, reason: str, code: str, message: str) -> None:
        self.transport.write(error_response(status, reason, code, message))
        self.transport.close()

    def data_received(self, data: bytes) -> None:
        if self.transport.is_closing():
            return  # refused or evicted: nothing more is parsed
        if self._in_headers:
            self._header_bytes += len(data)
        super().data_received(data)
        if (self._in_headers and self._header_bytes > self.limits.max_header_bytes
                and not self.transport.is_closing()):
            self._cancel_header_timer()
            self.parser = None  # type: ignore[assignment]  # frees what it buffered
            self._refuse(431, "Request Header Fields Too Large", "headers_too_large",
                         f"the request line and headers exceed {self.limits.max_header_bytes} "
                         "bytes")

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._in_headers = True

    def on_headers_complete(self) -> None:
        self._in_headers = False
        self._header_bytes = 0
        self._cancel_header_timer()
        refusal = self._cross_site_refusal()
        if refusal is not None:
            app, self.app = self.app, refusal
            try:
                super().on_headers_complete()
            finally:
                self.app = app
            return
        limit = self.limits.max_connections
        over = len(self.connections) > limit and len(self._open_peers()) > limit
        if over and httptools.parse_url(self.url).path not in ALWAYS_ANSWERED:
            app, self.app = self.app, _busy_app
            try:
                super().on_headers_complete()
            finally:
                self.app = app
            return
        super().on_headers_complete()

    def _cross_site_refusal(self) -> Any:
        """The app answering a tokenless request a web page could have sent, or None."""
        hosts = self.limits.hosts
        if hosts is None:
            return None
        headers = dict(self.headers)
        host = headers.get(b"host")
        if host is not None and host_name(host.decode("latin-1")) not in hosts:
            return _answer(403, "host", "the Host header names another server (a server "
                           "without a token answers its own address only)")
        method = self.parser.get_method()
        if method in WRITE_METHODS:
            kind = headers.get(b"content-type", b"").split(b";")[0].strip().lower()
            browser = b"origin" in headers or b"sec-fetch-mode" in headers
            if kind not in WRITE_TYPES and not kind.startswith(b"image/") and (kind or browser):
                return _answer(415, "unsupported_media_type", "a write needs the content type "
                               "application/json, application/octet-stream or image/*")
        return None

    def on_response_complete(self) -> None:
        self._served += 1
        self._quiet_since = self.loop.time()
        if self.cycle is not None:
            self.cycle.body = bytearray()  # an unread body is not kept
        super().on_response_complete()
        if not self.transport.is_closing() and not self.pipeline:
            self._in_headers = True
            self._header_bytes = 0
            self._arm_header_timer()


WRITE_METHODS = frozenset({b"POST", b"PUT", b"PATCH", b"DELETE"})
WRITE_TYPES = frozenset({b"application/json", b"application/octet-stream"})


def host_name(header: str) -> str:
    """The name of a ``Host`` header, lower case, without its port (``[::1]:80`` -> ``[::1]``)."""
    value = header.strip().lower()
    if value.startswith("["):
        return value.partition("]")[0] + "]"
    return value.rpartition(":")[0] if value.count(":") == 1 else value


def _answer(status: int, code: str, message: str) -> Any:
    body = json.dumps({"error": code, "message": message}, separators=(",", ":")).encode()

    async def app(scope: Any, receive: Any, send: Any) -> None:
        await send({"type": "http.response.start", "status": status, "headers": [
            (b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
            (b"connection", b"close")]})
        await send({"type": "http.response.body", "body": body})

    return app


async def _busy_app(scope: Any, receive: Any, send: Any) -> None:
    """The answer to a request beyond the connection limit (every connection busy)."""
    body = json.dumps({"error": "busy", "message": "the server's connections are all busy; "
                       "retry later"}, separators=(",", ":")).encode()
    await send({"type": "http.response.start", "status": 503, "headers": [
        (b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
        (b"retry-after", b"1"), (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body})
