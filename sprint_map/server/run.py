"""serve_map(): open the map for writing, bind, run uvicorn until SIGTERM/SIGINT, close.

uvicorn handles SIGTERM and SIGINT gracefully: it stops accepting connections, lets requests in
progress finish (up to ``shutdown_grace_s``), then runs the app's lifespan shutdown, which
finishes or discards open sessions, stops the writer after its queue and closes the map
(persisting the index). A SIGKILL loses nothing acknowledged: a commit is answered only after
its LMDB transaction returned.
"""

from __future__ import annotations

import os
import signal
import socket
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING

from sprint_map.errors import ListenError
from sprint_map.map import SprintMap
from sprint_map.server.auth import check_bind, load_token, served_hosts
from sprint_map.server.config import ServerConfig

if TYPE_CHECKING:  # FastAPI loads with the app, when serving starts
    from sprint_map.server.app import AppExtension


__all__ = ["bind", "serve_map"]


def bind(host: str, port: int) -> socket.socket:
    """A listening TCP socket on ``host:port`` (port 0: a free one).

    Raises
    ------
    ListenError
        The address is in use or not one of this host's.
    """
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        family, kind, proto, _, address = infos[0]
        sock = socket.socket(family, kind, proto)
    except OSError as exc:
        raise ListenError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from exc
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(2048)
    except OSError as exc:
        sock.close()
        raise ListenError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from exc
    sock.set_inheritable(True)
    return sock


def serve_map(path: str | os.PathLike[str], config: ServerConfig,
              announce: Callable[[str], None] | None = None, *, ray: str | None = None,
              replicas: int = 2, extensions: Sequence[AppExtension] = ()) -> None:
    """Serve the map at ``path`` until a shutdown signal; ``extensions`` add routes to the
    app (:func:`sprint_map.server.app.create_app`).

    With ``ray`` (``local``, ``auto`` or an address) the sessions' localisers run in
    ``replicas`` Ray actors (:mod:`sprint_map.fleet.replicas`); commits stay in this process.

    ``announce`` receives one line once the socket listens (default: printed to stdout):
    ``serving MAP on http://HOST:PORT``; with port 0 it names the port picked.

    Raises
    ------
    UnsafeServeError
        A non-loopback host without a token.
    ListenError, NotAMapError, MapLockedError, ...
        Before anything is served.
    """
    import uvicorn

    from sprint_map.server.app import create_app
    from sprint_map.server.guard import ConnectionLimits, guarded_protocol
    from sprint_map.server.service import LocalisationService

    token = load_token(config)
    check_bind(config.host, token)
    sock = bind(config.host, config.port)  # first: an address in use leaves the map untouched
    try:
        smap = SprintMap.open(path)
    except BaseException:
        sock.close()
        raise
    pool = None
    try:
        if ray is not None:  # Ray is imported from here on only
            from sprint_map.fleet.replicas import ReplicaPool
            from sprint_map.fleet.runtime import connect

            connect(ray)
            pool = ReplicaPool(str(smap.path), replicas)
    except BaseException:
        sock.close()
        smap.close()
        raise
    # This process is the server: its start-up heap is frozen once ready (server/heap.py).
    service = LocalisationService(smap, config, localizers=pool.localizer if pool else None,
                                  settle_heap=True)
    app = create_app(service, token, extensions)
    # The connection limits uvicorn's httptools protocol lacks (header deadline and size, a
    # connection limit that never refuses /healthz): see server/guard.py. The token and the
    # body's size and time are checked by the app's RequestGuard, before the body is read.
    protocol = guarded_protocol(ConnectionLimits(
        config.max_connections, config.max_header_bytes, config.header_timeout_s,
        served_hosts(config.host, token, config.allowed_hosts)))
    server = uvicorn.Server(uvicorn.Config(
        app, http=protocol, log_level="warning", access_log=False, lifespan="on",
        limit_concurrency=None,  # guard.py's limit instead (uvicorn's counts idle connections)
        timeout_keep_alive=config.keep_alive_s,  # type: ignore[arg-type]  # float is fine
        timeout_graceful_shutdown=int(max(1, round(config.shutdown_grace_s))),
        h11_max_incomplete_event_size=config.max_header_bytes,  # were h11 ever used
    ))
    host, port = sock.getsockname()[:2]
    shown = f"[{host}]" if ":" in host else host
    line = f"serving {Path(path)} on http://{shown}:{port}"
    (announce or (lambda text: print(text, flush=True)))(line)
    # uvicorn re-raises the signal that stopped it once it has shut down gracefully, to the
    # handlers that were installed before it ran: make those no-ops, so that a graceful stop
    # ends with exit status 0 (not "killed by SIGTERM", nor a KeyboardInterrupt traceback).
    previous = {sig: signal.signal(sig, _ignore) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        server.run(sockets=[sock])
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        sock.close()
        if pool is not None:
            pool.close()
        if not smap.closed:  # the lifespan did not run (start-up failed)
            smap.close()
        for warning in smap.warnings:
            print(f"Warning: {warning}", file=sys.stderr)
    if not server.started:
        raise ListenError(f"the server did not start on {host}:{port} (see the log above)")


def _ignore(sig: int, frame: FrameType | None) -> None:
    """A signal handler that does nothing (see :func:`serve_map`)."""
