"""Retrieval shards on a real 3-node Ray cluster: the fanned-out exact search equals the
in-process one, ids and distances, over the socket channel and over Ray calls; a shard killed
is a clear ReplicaLostError."""

from __future__ import annotations

import os
import signal
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sprint_map.config import MapConfig, StoreOptions
from sprint_map.errors import ReplicaLostError
from sprint_map.fleet import shards as shards_module
from sprint_map.fleet.channel import ChannelError
from sprint_map.fleet.shards import ALIGN, ShardedIndex, ShardWorker, merge_topk, plan_ranges
from sprint_map.map import SprintMap

pytestmark = pytest.mark.ray

DIM = 24


def build(path: Path, rng: np.random.Generator, lengths: list[int]) -> SprintMap:
    smap = SprintMap.create(path, MapConfig(dim=DIM, store=StoreOptions(index_type="flat", shard_rows=3000)))
    for n, length in enumerate(lengths):
        smap.add_sequence(rng.standard_normal((length, DIM)).astype(np.float32), name=f"d{n}")
    return smap


@pytest.mark.parametrize(("vertices", "shards"), [(0, 3), (10, 3), (5000, 3), (5000, 1),
                                                  (ALIGN * 7 + 5, 3)])
def test_plan_ranges_tile_the_vertex_ids(vertices: int, shards: int) -> None:
    ranges = plan_ranges(vertices, shards)
    assert ranges[0][0] == 0 and ranges[-1][1] is None
    assert 1 <= len(ranges) <= shards
    for (_, b), (a2, _) in zip(ranges, ranges[1:], strict=False):
        assert b == a2 and b is not None and b % ALIGN == 0


def test_merge_topk_pads_and_prefers_earlier_on_ties() -> None:
    d = [np.array([[1.0, 3.0]], np.float32), np.array([[1.0, 2.0]], np.float32)]
    i = [np.array([[5, 6]]), np.array([[9, -1]])]
    out_d, out_i = merge_topk(d, i, 4)
    assert out_i.tolist() == [[5, 9, 6, -1]]
    assert out_d[0, :3].tolist() == [1.0, 1.0, 3.0]


def unreachable(*args: Any, **kwargs: Any) -> None:
    raise ChannelError("connection refused (a firewall, in this test)")


@pytest.mark.parametrize(("ship", "transport"),
                         [(False, "socket"), (True, "socket"), (False, "ray")],
                         ids=["shared-fs", "shipped", "ray-calls"])
def test_fanned_out_search_equals_in_process(cluster: object, tmp_path: Path,
                                             rng: np.random.Generator, ship: bool,
                                             transport: str,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    if transport == "ray":  # what "auto" does when the shards' ports cannot be reached
        monkeypatch.setattr(shards_module, "ChannelClient", unreachable)
    with build(tmp_path / "m", rng, [2500, 1700, 3100]) as smap:
        sharded = ShardedIndex(smap, 3, ship=ship)
        try:
            assert len(sharded.actors) == 3
            assert sharded.transport == transport
            for nq in (1, 5, 40, 300, 800):  # 800: past 64 KB, through the object store
                q = rng.standard_normal((nq, DIM)).astype(np.float32)
                want_d, want_i = smap.search(q, 10)
                got_d, got_i = sharded.search_live(q, 10)
                np.testing.assert_array_equal(got_i, want_i)
                np.testing.assert_array_equal(got_d, want_d)  # bit for bit
            # commits after the shards were made: the open-ended shard catches up
            smap.add_sequence(rng.standard_normal((900, DIM)).astype(np.float32), name="late")
            smap.remove_sequences(["d1"])
            assert sharded.catch_up(smap) == smap.stats()["vertices"]
            q = np.concatenate([smap.descriptors(3)[:20],
                                rng.standard_normal((20, DIM)).astype(np.float32)])
            want_d, want_i = smap.search(q, 10)
            got_d, got_i = sharded.search_live(q, 10)
            np.testing.assert_array_equal(got_i, want_i)
            np.testing.assert_array_equal(got_d, want_d)
            assert (got_i[:20, 0] >= smap.sequence(3).first_vertex).all()
            # searches from several threads at once (the channel serialises its exchanges)
            batches = [rng.standard_normal((n, DIM)).astype(np.float32) for n in (1, 7, 33)]
            wants = [smap.search(b, 5) for b in batches]
            results: dict[int, Any] = {}

            def run(n: int) -> None:
                results[n] = [sharded.search_live(batches[n], 5) for _ in range(5)]

            threads = [threading.Thread(target=run, args=(n,)) for n in range(len(batches))]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            for n, want in enumerate(wants):
                for got in results[n]:
                    np.testing.assert_array_equal(got[1], want[1])
                    np.testing.assert_array_equal(got[0], want[0])
        finally:
            sharded.close()


def test_socket_transport_required_fails_clearly(cluster: object, tmp_path: Path,
                                                 rng: np.random.Generator,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(shards_module, "ChannelClient", unreachable)
    with build(tmp_path / "m", rng, [1500]) as smap, pytest.raises(ChannelError,
                                                                   match="firewall"):
        ShardedIndex(smap, 1, transport="socket")
    with pytest.raises(ValueError, match="transport"):
        ShardedIndex(smap, 1, transport="grpc")


@pytest.mark.parametrize("transport", ["socket", "ray"])
def test_a_killed_shard_is_a_clear_error(cluster: object, tmp_path: Path,
                                         rng: np.random.Generator, transport: str) -> None:
    import ray

    with build(tmp_path / "m", rng, [2500, 2000]) as smap:
        sharded = ShardedIndex(smap, 3, transport=transport)
        try:
            q = rng.standard_normal((4, DIM)).astype(np.float32)
            sharded.search(q, 5)
            pid = ray.get(sharded.actors[1].pid.remote())
            os.kill(pid, signal.SIGKILL)  # runs no more code: its connection closes
            with pytest.raises(ReplicaLostError, match="retrieval shard"):
                sharded.search(q, 5)
            with pytest.raises(ReplicaLostError, match="make a new"):  # and stays so
                sharded.search(q, 5)
        finally:
            sharded.close()


def test_actors_are_spread_over_the_nodes(cluster: object, tmp_path: Path,
                                          rng: np.random.Generator) -> None:
    import ray

    with build(tmp_path / "m", rng, [4000]) as smap:
        sharded = ShardedIndex(smap, 3)
        try:
            nodes = ray.get([a.node.remote() for a in sharded.actors])
            assert len(set(nodes)) == 3
        finally:
            sharded.close()


def build_segmented(path: Path, rng: np.random.Generator, lengths: list[int]) -> SprintMap:
    """A map searched by its approximate index: segments of 512 rows, merged up to 1,024."""
    centres = rng.standard_normal((200, DIM)).astype(np.float32)
    options = StoreOptions(index_type="ivf-pq", index_nlist=32, index_nprobe=8,
                           index_segment_rows=512, index_merge_factor=2,
                           index_segment_max_rows=1024, index_train_sample=2000,
                           index_rerank=40, shard_rows=3000)
    smap = SprintMap.create(path, MapConfig(dim=DIM, store=options))
    for n, length in enumerate(lengths):
        rows = centres[rng.integers(len(centres), size=length)]
        smap.add_sequence(rows + 0.2 * rng.standard_normal((length, DIM)).astype(np.float32),
                          name=f"d{n}")
    smap.flush()  # every full block sealed (a commit seals in the background)
    return smap


def test_approximate_shards_search_their_segments(cluster: object, tmp_path: Path,
                                                  rng: np.random.Generator) -> None:
    with build_segmented(tmp_path / "m", rng, [2500, 1700, 3100]) as smap:
        segments = smap.index_segments()
        assert max(b - a for a, b in segments) == 1024  # merges stop at index_segment_max_rows
        sharded = ShardedIndex(smap, 3, approximate=True)
        try:
            ends = {b for _, b in segments}
            assert len(sharded.actors) == 3 and sharded.ranges[-1][1] is None
            assert all(b in ends for _, b in sharded.ranges[:-1])  # cut at segment ends
            q = np.concatenate([smap.vertex_rows(0)[::97],
                                rng.standard_normal((20, DIM)).astype(np.float32)])
            got = sharded.search_live(q, 10)
            # each shard answers what the map answers within its range; merged, the k best
            parts = [smap.search_within(q, 10, a, b) for a, b in sharded.ranges]
            want = merge_topk([p[0] for p in parts], [p[1] for p in parts], 10)
            np.testing.assert_array_equal(got[1], want[1])
            np.testing.assert_array_equal(got[0], want[0])
            rows = len(smap.vertex_rows(0)[::97])
            np.testing.assert_array_equal(got[1][:rows, 0], np.arange(0, 7300, 97))
            # commits after the shards were made: the open-ended shard searches them
            smap.add_sequence(smap.vertex_rows(0, 300) + 0.01, name="late")
            smap.remove_sequences(["d1"])
            assert sharded.catch_up(smap) == smap.stats()["vertices"]
            _, ids = sharded.search_live(smap.vertex_rows(7300, 7310), 3)
            assert (ids[:, 0] >= 7300).all() or (ids[:, 0] < 300).all()
            _, ids = sharded.search_live(smap.vertex_rows(2500, 2600), 10)
            assert not ((ids >= 2500) & (ids < 4200)).any()  # d1 removed: hidden
        finally:
            sharded.close()
    with build(tmp_path / "flat", rng, [1500]) as smap:
        with pytest.raises(ValueError, match="exact"):
            ShardedIndex(smap, 2, approximate=True)
        with pytest.raises(ValueError, match="shared filesystem"):
            ShardedIndex(smap, 2, approximate=True, ship=True)


def test_a_shard_refuses_rows_out_of_its_range() -> None:
    worker = ShardWorker(None, 0, ALIGN, 4, np.zeros((10, 4), np.float32))
    with pytest.raises(ValueError, match="cannot add"):
        worker.append(20, np.zeros((1, 4), np.float32))
    with pytest.raises(ValueError, match="past the shard"):
        worker.append(10, np.zeros((ALIGN, 4), np.float32))
