"""The shards' search channel (a TCP connection per shard), without Ray: requests answered in
order, bytes intact, a shard's own error reported, a wrong token or a dead peer a ChannelError."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from sprint_map.fleet.channel import TOKEN_BYTES, ChannelClient, ChannelError, ChannelServer
from sprint_map.util.arrays import Descriptors, SearchResult

DIM = 6
TOKEN = bytes(range(TOKEN_BYTES))


def handler(queries: Descriptors, k: int) -> SearchResult:
    """A deterministic answer that depends on every byte of the queries and on k."""
    if k == 99:
        raise ValueError("k 99 refused")
    if k == 98:
        time.sleep(3)
    sums = queries.astype(np.float64).sum(axis=1, keepdims=True)
    d = (sums + np.arange(k)).astype(np.float32)
    i = (np.arange(len(queries))[:, None] * 1000 + np.arange(k) - 1).astype(np.int64)
    return d, i


@pytest.fixture
def server() -> Iterator[ChannelServer]:
    s = ChannelServer(handler, DIM, TOKEN, "127.0.0.1")
    yield s
    s.close()


def test_requests_are_answered_in_order_bytes_intact(server: ChannelServer,
                                                     rng: np.random.Generator) -> None:
    client = ChannelClient(server.address, TOKEN, DIM)
    try:
        client.ping()
        for nq, k in [(1, 10), (17, 3), (300, 1), (2, 7)]:
            q = rng.standard_normal((nq, DIM)).astype(np.float32)
            client.send(q, k)
            d, i = client.receive(nq, k)
            want_d, want_i = handler(q, k)
            np.testing.assert_array_equal(d, want_d)
            np.testing.assert_array_equal(i, want_i)
            assert d.dtype == np.float32 and i.dtype == np.int64 and i.shape == (nq, k)
        with pytest.raises(RuntimeError, match="k 99 refused"):  # the shard's own error
            client.send(np.zeros((2, DIM), np.float32), 99)
            client.receive(2, 99)
        client.ping()  # and the channel goes on
        with pytest.raises(ValueError, match="float32"):
            client.send(np.zeros((2, DIM + 1), np.float32), 3)
    finally:
        client.close()


def test_two_clients_at_once(server: ChannelServer, rng: np.random.Generator) -> None:
    clients = [ChannelClient(server.address, TOKEN, DIM) for _ in range(2)]
    queries = [rng.standard_normal((5, DIM)).astype(np.float32) for _ in clients]
    for client, q in zip(clients, queries, strict=True):
        client.send(q, 4)
    for client, q in zip(reversed(clients), reversed(queries), strict=True):
        np.testing.assert_array_equal(client.receive(5, 4)[1], handler(q, 4)[1])
        client.close()


def test_a_wrong_token_is_refused(server: ChannelServer) -> None:
    client = ChannelClient(server.address, bytes(TOKEN_BYTES), DIM)
    try:
        with pytest.raises(ChannelError):
            client.ping()
    finally:
        client.close()


def test_a_slow_shard_times_out(server: ChannelServer) -> None:
    client = ChannelClient(server.address, TOKEN, DIM, timeout=0.3)
    try:
        client.send(np.zeros((1, DIM), np.float32), 98)  # answers after 3 s
        with pytest.raises(ChannelError, match="no answer"):
            client.receive(1, 98)
    finally:
        client.close()


def test_a_peer_that_goes_away_is_a_channel_error() -> None:
    listener = socket.create_server(("127.0.0.1", 0))
    address = listener.getsockname()[:2]

    def accept_and_drop() -> None:
        conn, _ = listener.accept()
        conn.recv(TOKEN_BYTES)
        conn.close()

    thread = threading.Thread(target=accept_and_drop)
    thread.start()
    client = ChannelClient(address, TOKEN, DIM)
    try:
        thread.join()
        with pytest.raises(ChannelError):
            client.send(np.zeros((1, DIM), np.float32), 2)
            client.receive(1, 2)
    finally:
        client.close()
        listener.close()
    with pytest.raises(ChannelError, match="cannot reach"):  # nobody listens there now
        ChannelClient(address, TOKEN, DIM)
