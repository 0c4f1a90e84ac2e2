"""The search data plane of the retrieval shards: one TCP connection from the caller to each shard.

A Ray actor call costs ~0.5-0.8 ms of CPU on this 2-core machine (task submission, gRPC, the
serialisation of numpy arguments and results), so a fan-out to three shards paid 1.4-2.2 ms
before any shard searched (``docs/benchmarks.md``, "Ray: retrieval shards and the ingest farm"). Ray keeps the control plane (placing
the actors, loading and catching up their ranges, killing them); the searches go over a plain
socket per shard: the caller writes the query rows as raw float32 bytes, the shard answers with
its ids and distances as raw int64 and float32 bytes. A round trip to three shards then costs
~0.06 ms on a quiet machine, 0.13-0.37 ms p50 at load 4-12.

Protocol (little-endian; one request at a time per connection, answered in order):

- the client opens with the ``TOKEN_BYTES`` token the shard was given through Ray (a connection
  that does not is closed: the port is on the cluster's network);
- request: ``uint32 queries, uint32 k``, then ``queries * dim`` float32 (``queries`` 0: a ping);
- reply: ``uint8 status, uint64 length``, then ``length`` bytes: for ``OK`` the ids
  (``queries * k`` int64) then the distances (``queries * k`` float32; ids first keeps both
  aligned in the buffer), for ``FAILED`` the shard's error message (UTF-8).

A connection that closes, resets or times out is a lost shard (:class:`ChannelError`): the
caller cannot tell how far the exchange went, so the channel is not used again.
"""

from __future__ import annotations

import contextlib
import hmac
import socket
import struct
import threading
from collections.abc import Callable

import numpy as np

from sprint_map.util.arrays import Descriptors, SearchResult

__all__ = ["CONNECT_TIMEOUT", "FAILED", "OK", "TOKEN_BYTES", "ChannelClient", "ChannelError",
           "ChannelServer", "pack_result", "recv_exact", "unpack_result"]

TOKEN_BYTES = 16
OK, FAILED = 0, 1
#: Seconds a connection may take to open (a firewalled port fails within it).
CONNECT_TIMEOUT = 5.0
_REQUEST = struct.Struct("<II")
_REPLY = struct.Struct("<BQ")

#: What a shard runs for a request: ``(queries (n, dim) float32, k) -> (distances, ids)``.
Handler = Callable[[Descriptors, int], SearchResult]


class ChannelError(ConnectionError):
    """The shard at the other end is gone, unreachable, too slow or refused the token."""


def recv_exact(sock: socket.socket, n: int) -> bytearray:
    """Exactly ``n`` bytes from ``sock`` (:class:`ChannelError` if it closes first)."""
    buf = bytearray(n)
    view = memoryview(buf)
    got = 0
    while got < n:
        r = sock.recv_into(view[got:])
        if not r:
            raise ChannelError(f"connection closed after {got} of {n} bytes")
        got += r
    return buf


def pack_result(result: SearchResult) -> bytes:
    """``(distances, ids)`` as one buffer: the ids (int64) then the distances (float32).
    (Also what a shard returns through a Ray call: one bytes object pickles far cheaper than
    two numpy arrays.)"""
    d, i = result
    return np.ascontiguousarray(i, np.int64).tobytes() + np.ascontiguousarray(
        d, np.float32).tobytes()


def unpack_result(payload: bytes | bytearray, nq: int, k: int) -> SearchResult:
    """The ``(distances, ids)``, each ``(nq, k)``, of :func:`pack_result`'s buffer (views of
    it, no copy)."""
    i = np.frombuffer(payload, np.int64, nq * k).reshape(nq, k)
    d = np.frombuffer(payload, np.float32, nq * k, offset=nq * k * 8).reshape(nq, k)
    return d, i


def _nodelay(sock: socket.socket) -> socket.socket:
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


class ChannelServer:
    """Answers search requests on ``host`` (an ephemeral port), one thread per connection.

    Parameters
    ----------
    handler : callable
        ``(queries, k) -> (distances, ids)``; it must be safe to call beside the owner's other
        methods (the shard takes its own lock).
    dim : int
        Columns of a query row.
    token : bytes
        What a client must send first (``TOKEN_BYTES`` bytes).
    host : str
        The address to listen on (the node's IP on a cluster).

    Notes
    -----
    Per request: two ``recv`` and one ``sendall`` besides the handler; the rows are read into
    one buffer and viewed as float32 without a copy.
    """

    def __init__(self, handler: Handler, dim: int, token: bytes, host: str) -> None:
        if len(token) != TOKEN_BYTES:
            raise ValueError(f"a channel token is {TOKEN_BYTES} bytes")
        self.handler = handler
        self.dim = dim
        self._token = token
        self._listener = socket.create_server((host, 0))
        self.address: tuple[str, int] = self._listener.getsockname()[:2]
        self._closed = False
        threading.Thread(target=self._accept, name="shard-channel", daemon=True).start()

    def _accept(self) -> None:
        while not self._closed:
            try:
                conn, _ = self._listener.accept()
            except OSError:  # closed
                return
            threading.Thread(target=self._serve, args=(_nodelay(conn),), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        with conn, contextlib.suppress(OSError):  # the client went away: nothing to answer
            if not hmac.compare_digest(bytes(recv_exact(conn, TOKEN_BYTES)), self._token):
                return
            while True:
                nq, k = _REQUEST.unpack(recv_exact(conn, _REQUEST.size))
                if not nq:  # a ping
                    conn.sendall(_REPLY.pack(OK, 0))
                    continue
                queries = np.frombuffer(recv_exact(conn, nq * self.dim * 4), np.float32)
                try:
                    payload = pack_result(self.handler(queries.reshape(nq, self.dim), k))
                    status = OK
                except Exception as exc:  # reported to the caller, the shard serves on
                    payload = f"{type(exc).__name__}: {exc}".encode()
                    status = FAILED
                conn.sendall(_REPLY.pack(status, len(payload)) + payload)

    def close(self) -> None:
        """Stop accepting connections (open ones end with the process)."""
        self._closed = True
        with contextlib.suppress(OSError):
            self._listener.close()


class ChannelClient:
    """The caller's end of one shard's channel.

    A search is :meth:`send` then :meth:`receive`, so that a caller can send to every shard
    before reading any answer (the shards search at once). Not thread-safe: the caller
    serialises its exchanges.

    Parameters
    ----------
    address : (host, port)
        The shard's :attr:`ChannelServer.address`.
    token : bytes
        The token the shard was given.
    dim : int
        Columns of a query row.
    timeout : float
        Seconds any one send or receive may take before the shard counts as lost (opening
        the connection: at most ``CONNECT_TIMEOUT``).
    """

    def __init__(self, address: tuple[str, int], token: bytes, dim: int,
                 timeout: float = 60.0) -> None:
        self.dim = dim
        try:
            self._sock = _nodelay(socket.create_connection(
                address, timeout=min(timeout, CONNECT_TIMEOUT)))
            self._sock.settimeout(timeout)
            self._sock.sendall(token)
        except OSError as exc:
            raise ChannelError(f"cannot reach the shard at {address[0]}:{address[1]}: "
                               f"{exc}") from exc

    def send(self, queries: Descriptors, k: int) -> None:
        """Send one request (``queries`` (n, dim) float32, C-contiguous; none: a ping)."""
        if queries.shape[1:] != (self.dim,) or queries.dtype != np.float32:
            raise ValueError(f"queries must be (n, {self.dim}) float32")
        try:
            self._sock.sendall(_REQUEST.pack(len(queries), k) + queries.tobytes())
        except OSError as exc:
            raise ChannelError(f"sending to the shard failed: {exc}") from exc

    def receive(self, nq: int, k: int) -> SearchResult:
        """The reply to the request of ``nq`` queries sent last: ``(distances, ids)``, each
        ``(nq, k)``. A shard's own error is raised as :class:`RuntimeError`."""
        try:
            status, length = _REPLY.unpack(recv_exact(self._sock, _REPLY.size))
            payload = recv_exact(self._sock, length)
        except OSError as exc:  # ChannelError included
            raise ChannelError(f"no answer from the shard: {exc}") from exc
        if status != OK:
            raise RuntimeError(f"the shard failed: {payload.decode(errors='replace')}")
        if length != nq * k * 12:
            raise ChannelError(f"the shard answered {length} bytes, not {nq * k * 12}")
        return unpack_result(payload, nq, k)

    def ping(self) -> None:
        """An empty round trip."""
        self.send(np.empty((0, self.dim), np.float32), 0)
        self.receive(0, 0)

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self._sock.close()
