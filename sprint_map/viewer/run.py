"""view_map(): open a map read-only, summarise it, serve the viewer page until SIGTERM/SIGINT."""

from __future__ import annotations

import os
import signal
import sys
import time
from collections.abc import Callable
from pathlib import Path
from types import FrameType

from sprint_map.viewer.live import LiveMap

__all__ = ["view_map"]


def view_map(path: str | os.PathLike[str], *, trace: str | os.PathLike[str] | None = None,
             host: str = "127.0.0.1", port: int = 8000, token_file: str | None = None,
             announce: Callable[[str], None] | None = None) -> None:
    """Serve the viewer of the map at ``path`` (opened read-only) until a shutdown signal.

    The map followed is the live generation (:class:`~sprint_map.viewer.live.LiveMap`); the
    connections are guarded as ``serve``'s are (:mod:`sprint_map.server.guard`, with
    :class:`~sprint_map.server.config.ServerConfig`'s defaults), the token checked before any
    body is read (:class:`~sprint_map.server.app.RequestGuard`).

    The overview is computed before the socket is announced, so the page's first request
    finds it ready. ``announce`` receives ``viewing MAP on http://HOST:PORT`` (default: printed
    to stdout); with port 0 it names the port picked.

    Raises
    ------
    UnsafeServeError
        A host beyond loopback without a token (``$SPRINT_MAP_TOKEN`` or ``token_file``).
    ListenError, NotAMapError, InputError, ...
        Before anything is served (``InputError``: the trace is not a readable trace).
    """
    import uvicorn

    from sprint_map import read_trace
    from sprint_map.server.auth import check_bind, load_token, served_hosts
    from sprint_map.server.config import ServerConfig
    from sprint_map.server.guard import ConnectionLimits, guarded_protocol
    from sprint_map.server.run import bind
    from sprint_map.viewer.app import create_view_app, page_html
    from sprint_map.viewer.overview import MapOverview

    config = ServerConfig(host=host, port=port, token_file=token_file)
    token = load_token(config)
    check_bind(host, token)
    shown_trace = read_trace(trace) if trace is not None else None
    sock = bind(host, port)
    try:
        live = LiveMap(path)
    except BaseException:
        sock.close()
        raise
    try:
        summary = MapOverview(live.map, live.read)
        live.on_switch = lambda fresh: setattr(summary, "map", fresh)
        start = time.perf_counter()
        summary.overview()
        page_html()
        ready_s = time.perf_counter() - start
        app = create_view_app(summary, shown_trace, token, config)
        # serve's connection guard: header deadline and size, connection limit, and without
        # a token the Host and content-type checks (server/guard.py).
        protocol = guarded_protocol(ConnectionLimits(
            config.max_connections, config.max_header_bytes, config.header_timeout_s,
            served_hosts(host, token, config.allowed_hosts)))
        server = uvicorn.Server(uvicorn.Config(
            app, http=protocol, log_level="warning", access_log=False, lifespan="off",
            limit_concurrency=None, timeout_keep_alive=config.keep_alive_s,  # type: ignore[arg-type]
            h11_max_incomplete_event_size=config.max_header_bytes))
        bound, bound_port = sock.getsockname()[:2]
        shown = f"[{bound}]" if ":" in bound else bound
        (announce or (lambda text: print(text, flush=True)))(
            f"viewing {Path(path)} on http://{shown}:{bound_port} "
            f"(summarised in {ready_s:.1f} s)")
        previous = {sig: signal.signal(sig, _ignore) for sig in (signal.SIGTERM, signal.SIGINT)}
        try:
            server.run(sockets=[sock])
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
    finally:
        sock.close()
        live.close()
        for warning in live.warnings:
            print(f"Warning: {warning}", file=sys.stderr)


def _ignore(sig: int, frame: FrameType | None) -> None:
    """A no-op handler: uvicorn re-raises the signal that stopped it to the previous one."""
