"""ServerConfig: the service's limits and settings (frozen, with defaults, JSON round-trip)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from sprint_map.util import dataclass_dict

__all__ = ["SHUTDOWN_MODES", "ServerConfig"]

#: What graceful shutdown does with sessions still open: drop them, or commit those with frames.
SHUTDOWN_MODES = ("discard", "commit")


@dataclass(frozen=True)
class ServerConfig:
    """Settings of ``sprint-map serve``; every limit answers a clear 4xx/503, never grows memory.

    Each field is described by the comment above it.
    """

    #: Where to listen; loopback by default. Port 0 picks a free port (printed at start).
    host: str = "127.0.0.1"
    port: int = 8000
    #: Environment variable holding the bearer token.
    token_env: str = "SPRINT_MAP_TOKEN"
    #: File holding the bearer token (takes precedence over ``token_env``). Without a token the
    #: server refuses to listen on a non-loopback address.
    token_file: str | None = None
    #: Largest request body (a frame's JSON or image bytes); larger: 413.
    max_request_bytes: int = 4 << 20
    #: Open sessions at once; more: 503.
    max_sessions: int = 256
    #: Frames one session may stream before it must commit or be discarded; more: 409.
    max_frames_per_session: int = 100_000
    #: Descriptor bytes held by all open sessions together (they are committed at the end of a
    #: drive, so they stay in memory until then); more: 503.
    max_buffered_bytes: int = 2 << 30
    #: A session without a request for this long expires and is discarded.
    session_ttl_s: float = 600.0
    #: Threads answering frames (retrieval and HMM; FAISS and OpenCV release the GIL).
    frame_workers: int = 4
    #: Requests of one session waiting behind the frame in progress; more: 429.
    max_pending_frames: int = 8
    #: Frame requests admitted over all sessions (waiting or in progress); more: 503.
    max_queued_frames: int = 512
    #: Commits waiting for the single writer thread; more: 503.
    commit_queue_size: int = 16
    #: ``"discard"`` or ``"commit"`` the sessions still open at a graceful shutdown.
    on_shutdown: str = "discard"
    #: Open connections. A new connection beyond it closes the idle connection least worth keeping
    #: (one that never completed a request first, then the longest quiet); one with a request in
    #: progress is never closed. If all are busy, requests beyond it are answered 503 ``busy``, but
    #: ``/healthz`` and ``/readyz`` still answer (:mod:`.guard`). With ``max_request_bytes`` and
    #: ``max_header_bytes`` it bounds the memory held by requests.
    max_connections: int = 512
    #: Largest request line plus headers; larger: 431 and the connection is closed.
    max_header_bytes: int = 16 << 10
    #: A request's headers must be complete this long after its connection opened (or its previous
    #: response ended); otherwise 408 (or a silent close if nothing came).
    header_timeout_s: float = 10.0
    #: A request's whole body must arrive within this; otherwise 408.
    body_timeout_s: float = 30.0
    #: An idle keep-alive connection is closed after this (uvicorn ``timeout_keep_alive``).
    keep_alive_s: float = 5.0
    #: How long a graceful shutdown waits for requests in progress.
    shutdown_grace_s: float = 10.0
    #: Largest image frame, read from the image's header before it is decoded
    #: (:func:`sprint_map.frontend.imageheader.check_pixels`): a decompression bomb is refused
    #: (422), never decoded.
    max_image_pixels: int = 1 << 26
    #: How long after the oldest waiting frame the batcher may wait for more (while fewer wait than
    #: its previous batch held) before one index search of them all (:mod:`.batcher`); 0 searches
    #: what is waiting without waiting more.
    batch_window_ms: float = 2.0
    #: Most frames per batched search; 0 turns batching off (each frame searched alone by a frame
    #: worker, as before batching: the benchmark's baseline).
    batch_max_frames: int = 64
    #: OpenMP threads of the batched search (1: the other core answers HTTP).
    search_threads: int = 1
    #: Without a token, ``Host`` names answered beside the bound address and the loopback names
    #: (``localhost``, ``127.0.0.1``, ``[::1]``); any other is refused 403 (DNS rebinding).
    allowed_hosts: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not isinstance(self.port, int) or not 0 <= self.port <= 65535:
            raise ValueError("port must be in 0..65535")
        for name in ("max_request_bytes", "max_sessions", "max_frames_per_session",
                     "max_buffered_bytes", "frame_workers", "max_pending_frames",
                     "max_queued_frames", "commit_queue_size", "max_connections",
                     "max_image_pixels", "max_header_bytes"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive integer")
        for name in ("session_ttl_s", "shutdown_grace_s", "header_timeout_s", "body_timeout_s",
                     "keep_alive_s"):
            value = getattr(self, name)
            if (isinstance(value, bool) or not isinstance(value, int | float)
                    or not 0 < value < math.inf):
                raise ValueError(f"{name} must be a number > 0")
        for name, value in (("batch_window_ms", self.batch_window_ms),
                            ("batch_max_frames", self.batch_max_frames),
                            ("search_threads", self.search_threads)):
            if (isinstance(value, bool) or not isinstance(value, int | float)
                    or not 0 <= value < math.inf or (name != "batch_window_ms"
                                                      and not isinstance(value, int))):
                raise ValueError(f"{name} must be a number >= 0" if name == "batch_window_ms"
                                 else f"{name} must be an integer >= 0")
        if self.search_threads < 1:
            raise ValueError("search_threads must be a positive integer")
        if self.on_shutdown not in SHUTDOWN_MODES:
            raise ValueError(f"on_shutdown must be one of {', '.join(SHUTDOWN_MODES)}")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> ServerConfig:
        """Build from a dict (e.g. a ``--config`` JSON file); unknown keys are refused."""
        return dataclass_dict.from_dict(cls, data)

    def to_dict(self) -> dict[str, Any]:
        """Return a JSON-ready dict."""
        return dataclass_dict.to_dict(self)
