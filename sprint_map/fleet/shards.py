"""Retrieval shards: Ray actors that each own a vertex range of the index; a search fans out.

When a map's index outgrows one machine, it is cut into vertex ranges ``[a, b)``. A
:class:`ShardWorker`, run as a Ray actor, answers for one range; the last one is open-ended
and catches up with commits. :class:`ShardedIndex` (in the caller) sends each query batch to
every shard at once, gets each one's k best and merges them into the k best overall.

Two kinds of shard:

* *exact* (default): the range (aligned to ``ALIGN`` ids) held in an exact flat index. The
  answer equals the in-process exact search, ids and distances: each shard searches its
  rows as the map's flat index does (:class:`~sprint_map.util.exact_search.ExactFlat`: every
  distance a function of its two rows alone, ties ordered by vertex id), and the k best of
  the union of the ranges' k best (ranges in vertex order, so equal distances keep id order)
  are the k best of the whole. Memory ``4 * dim`` bytes per vertex, a scan of every row.
* *approximate* (``approximate=True``): the range cut at the map's index segment boundaries
  (:func:`plan_segment_ranges`; ``index_segment_max_rows`` keeps segments small enough to cut)
  and searched in the map's own approximate index, only over the segments holding it
  (``SprintMap.search_within``: its codes, probed lists and re-ranking from the map's files,
  which the actor reads on a shared filesystem). Each shard re-ranks its own
  ``index_rerank`` candidates, so the merged answer holds every candidate the in-process
  search re-ranks that is among a range's best, and more: its exact distances, at least the
  in-process recall. A query costs each shard its share of the codes.

Removed sequences are hidden as the store hides them (``SprintMap.removed_ranges().search_live``
over the fanned-out search; an approximate shard hides them itself).

How a search reaches the shards: by default over a direct TCP connection to each one
(:mod:`sprint_map.fleet.channel`: raw float32 queries out, raw ids and distances back), not a
Ray actor call per shard, whose task submission, gRPC and numpy serialisation cost more than a
small search (``docs/benchmarks.md``, "Ray: retrieval shards and the ingest farm"); Ray places, loads, catches up and ends the
actors. A shard lost (killed, its node gone) is a :class:`~sprint_map.errors.ReplicaLostError`.

Where the rows come from (``docs/fleet.md``, "Where the map files live"): with a shared
filesystem each actor opens the map read-only and reads its range itself (``ship=False``);
otherwise the caller reads the rows and ships them through Ray's object store (``ship=True``).
"""

from __future__ import annotations

import os
import secrets
import threading
from typing import Any

import numpy as np

from sprint_map.errors import ReplicaLostError
from sprint_map.fleet.channel import (
    TOKEN_BYTES,
    ChannelClient,
    ChannelError,
    ChannelServer,
    pack_result,
    unpack_result,
)
from sprint_map.map import SprintMap
from sprint_map.util.arrays import Descriptors, DescriptorsLike, SearchResult
from sprint_map.util.exact_search import ExactFlat
from sprint_map.util.lazy import faiss  # imported on first use
from sprint_map.util.validation import validate_descriptors

__all__ = ["ALIGN", "TRANSPORTS", "ShardWorker", "ShardedIndex", "alive_nodes", "merge_topk",
           "plan_ranges", "plan_segment_ranges", "spread"]

#: Shard boundaries are multiples of this many vertex ids.
ALIGN = 1024
#: Rows added to a shard's index per call when loading (bounds the copy of a memory map).
LOAD_CHUNK = 65536
PAD_DISTANCE = np.finfo(np.float32).max
#: How :class:`ShardedIndex` sends searches to the shards (see its ``transport``).
TRANSPORTS = ("auto", "socket", "ray")


def plan_ranges(vertices: int, shards: int, align: int = ALIGN) -> list[tuple[int, int | None]]:
    """``shards`` vertex ranges ``[a, b)`` tiling ``0..vertices``, boundaries multiples of
    ``align``; the last is open-ended (``b`` None: it takes the vertices committed later).
    Fewer ranges when the map is too small to give each one ``align`` ids."""
    if shards < 1:
        raise ValueError("shards must be >= 1")
    blocks = max(1, -(-vertices // align))
    shards = min(shards, blocks)
    cuts = [round(i * blocks / shards) * align for i in range(shards)]
    return [(a, b) for a, b in zip(cuts, cuts[1:], strict=False)] + [(cuts[-1], None)]


def plan_segment_ranges(segments: list[tuple[int, int]], shards: int
                        ) -> list[tuple[int, int | None]]:
    """At most ``shards`` vertex ranges ``[a, b)`` cut only at the ends of ``segments`` (the
    index's sealed segments, in order), each cut the segment end nearest to an equal share of
    the sealed vertices; the last range is open-ended (it takes the unsealed tail and later
    commits). O(shards * segments).

    >>> plan_segment_ranges([(0, 4), (4, 8), (8, 12), (12, 13)], 3)
    [(0, 4), (4, 8), (8, None)]
    >>> plan_segment_ranges([(0, 10)], 3)
    [(0, None)]
    """
    if shards < 1:
        raise ValueError("shards must be >= 1")
    sealed = segments[-1][1] if segments else 0
    ends = [stop for _, stop in segments[:-1]]
    cuts = [0]
    for n in range(1, shards):
        later = [e for e in ends if e > cuts[-1]]
        if not later:
            break
        cut = min(later, key=lambda e: abs(e - n * sealed / shards))
        cuts.append(cut)
    return [(a, b) for a, b in zip(cuts, cuts[1:], strict=False)] + [(cuts[-1], None)]


def merge_topk(dists: list[np.ndarray], ids: list[np.ndarray], k: int
               ) -> tuple[np.ndarray, np.ndarray]:
    """The k best of several ``(nq, k_i)`` result lists (distance ascending; on equal distances
    the earlier list first, -1 pads last). O(nq * m log m) for m = sum of k_i."""
    d = np.concatenate(dists, axis=1)
    i = np.concatenate(ids, axis=1)
    d = np.where(i >= 0, d, PAD_DISTANCE)
    order = np.argsort(d, axis=1, kind="stable")[:, :k]
    out_d = np.take_along_axis(d, order, axis=1)
    out_i = np.take_along_axis(i, order, axis=1)
    if out_d.shape[1] < k:  # fewer candidates than k in all: pad like FAISS
        pad = k - out_d.shape[1]
        out_d = np.pad(out_d, ((0, 0), (0, pad)), constant_values=PAD_DISTANCE)
        out_i = np.pad(out_i, ((0, 0), (0, pad)), constant_values=-1)
    return out_d.astype(np.float32, copy=False), out_i.astype(np.int64, copy=False)


def alive_nodes(ray: Any) -> list[str]:
    """Ids of the cluster's live nodes, in a stable order."""
    return sorted(node["NodeID"] for node in ray.nodes() if node.get("Alive"))


def spread(nodes: list[str], n: int) -> Any:
    """The scheduling strategy of the ``n``-th actor of a group: round robin over ``nodes``
    (hard: Ray's soft affinity was seen to stack actors on one node), so that S actors use
    min(S, nodes) nodes."""
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    if not nodes:
        return "SPREAD"
    return NodeAffinitySchedulingStrategy(nodes[n % len(nodes)], soft=False)


class ShardWorker:
    """One vertex range ``[start, stop)`` (``stop`` None: open-ended) of a map's index.

    Run as a Ray actor by :class:`ShardedIndex`; a plain object otherwise. Exact (default):
    with ``rows`` None the map at ``path`` is opened read-only and the range read from its
    shard files into a flat index (a shared filesystem); else ``rows`` are the range's
    descriptors, shipped by the caller. ``approximate``: the map at ``path`` is opened
    read-only and searched within the range (``SprintMap.search_within``).

    Notes
    -----
    Exact: ``4 * dim`` bytes per vertex held (the flat index's copy of the rows), a search of
    q queries O(q * rows * dim). Approximate: the map's codes of the range, memory-mapped; a
    search scans the range's share of the probed lists and re-ranks ``index_rerank`` rows.
    """

    def __init__(self, path: str | None, start: int, stop: int | None, dim: int,
                 rows: Descriptors | None = None, threads: int = 1,
                 approximate: bool = False) -> None:
        self.start = start
        self.threads = threads
        self.stop = stop
        self.dim = dim
        self.approximate = approximate
        self.index = faiss.IndexFlatL2(dim)
        self._exact: ExactFlat | None = None
        self.map: SprintMap | None = None
        # searches may come from the channel's thread while Ray calls load rows
        self._lock = threading.Lock()
        self._server: ChannelServer | None = None
        if rows is None or approximate:
            if path is None:
                raise ValueError("a shard needs the map's path or its rows"
                                 + (" (an approximate one: its path)" if approximate else ""))
            self.map = SprintMap.open(path, readonly=True)
            if approximate:
                self.map.search_within(np.zeros((1, dim), np.float32), 1, start, stop)
                return  # (ValueError here if the map's index is exact)
            total = self.map.stats()["vertices"]
            self._load(self.map, total if stop is None else min(stop, total))
        else:
            self.append(start, rows)

    def _load(self, smap: SprintMap, upto: int) -> None:
        at = self.covered()
        while at < upto:
            stop = min(upto, at + LOAD_CHUNK)
            rows = np.ascontiguousarray(smap.vertex_rows(at, stop), dtype=np.float32)
            with self._lock:
                self.index.add(rows)
            at = stop

    def covered(self) -> int:
        """One past the last vertex id this shard holds."""
        if self.approximate and self.map is not None:
            total = self.map.stats()["vertices"]
            return max(self.start, total if self.stop is None else min(self.stop, total))
        return self.start + int(self.index.ntotal)

    def append(self, first: int, rows: Descriptors) -> int:
        """Add ``rows`` as vertex ids ``first..`` (must continue the covered range)."""
        if self.approximate:
            raise ValueError("an approximate shard reads the map's files: no rows to ship")
        if first != self.covered():
            raise ValueError(f"shard covers up to {self.covered()}, cannot add at {first}")
        if self.stop is not None and first + len(rows) > self.stop:
            raise ValueError(f"rows past the shard's end {self.stop}")
        with self._lock:
            self.index.add(np.ascontiguousarray(rows, dtype=np.float32))
        return self.covered()

    def catch_up(self, committed: int) -> int:
        """Read the vertices committed since (open-ended shard on a shared filesystem)."""
        if self.map is not None and not self.approximate:  # approximate: each search does
            end = committed if self.stop is None else min(self.stop, committed)
            self._load(self.map, end)
        return self.covered()

    def search(self, queries: Descriptors, k: int) -> SearchResult:
        """k nearest of this range: ``(squared L2, global vertex ids)``, -1 padded (an
        approximate shard: live vertices only)."""
        if self.approximate and self.map is not None:
            with self._lock:
                return self.map.search_within(queries, k, self.start, self.stop)
        # One thread below 8 queries (latency-bound); the answer does not depend on it.
        faiss.omp_set_num_threads(1 if len(queries) < 8 else self.threads)
        with self._lock:
            if not self.index.ntotal:
                return (np.full((len(queries), k), PAD_DISTANCE, dtype=np.float32),
                        np.full((len(queries), k), -1, dtype=np.int64))
            if self._exact is None:
                self._exact = ExactFlat(self.index)
            d, i = self._exact.search(queries, k)  # certified: as the in-process search
        return d, np.where(i >= 0, i + self.start, -1)

    def search_packed(self, queries: Descriptors | bytes, k: int) -> bytes:
        """:meth:`search` for a Ray call: ``queries`` as an array or as raw float32 bytes, the
        answer as :func:`~sprint_map.fleet.channel.pack_result`'s one buffer (Ray pickles
        bytes far cheaper than numpy arrays)."""
        if isinstance(queries, bytes):
            queries = np.frombuffer(queries, np.float32).reshape(-1, self.dim)
        return pack_result(self.search(queries, k))

    def listen(self, token: bytes, host: str | None = None) -> tuple[str, int]:
        """Serve :meth:`search` over a direct TCP channel (:mod:`sprint_map.fleet.channel`)
        on ``host`` (default: this Ray node's IP); returns ``(host, port)``. Once per shard."""
        if self._server is None:
            if host is None:
                import ray

                node_ip: Any = ray.util.get_node_ip_address  # untyped in Ray
                host = str(node_ip())
            self._server = ChannelServer(self.search, self.dim, token, host)
        return self._server.address

    def pid(self) -> int:
        """The process running this shard (tests kill it)."""
        return os.getpid()

    def node(self) -> str:
        """The Ray node this actor runs on."""
        import ray

        return str(ray.get_runtime_context().get_node_id())

    def close(self) -> None:
        if self._server is not None:
            self._server.close()
            self._server = None
        if self.map is not None:
            self.map.close()
            self.map = None


class ShardedIndex:
    """k-NN over a map, fanned out to :class:`ShardWorker` actors (one per range).

    ``smap``: the map (its path, size and removed ranges are read here); ``shards``: vertex
    ranges (fewer for a tiny map: :func:`plan_ranges`, or with ``approximate`` fewer than its
    index segments allow: :func:`plan_segment_ranges`); ``approximate``: each shard searches
    its range in the map's approximate index (ValueError for a map whose index is exact, or
    with ``ship``), else an exact copy of its rows; ``ship``: read the rows here and send
    them to the actors (no shared filesystem; default: each actor reads its range from the
    map's files); ``threads``: OpenMP threads of a shard's search of 8 queries or more (default
    1: one shard per core); ``actor_options``: Ray options of the actors (default ``num_cpus=0``,
    no restart, round robin over the cluster's nodes); ``transport``: ``"socket"`` (a direct TCP
    connection to each shard, :mod:`sprint_map.fleet.channel`, on an ephemeral port the caller
    must reach), ``"ray"`` (one actor call per shard and search) or ``"auto"`` (socket, or Ray
    when a shard's port cannot be reached; :attr:`transport` says which); loading, catching up
    and closing always go through Ray. ``timeout``: seconds a shard may take on the socket
    before it counts as lost.

    One search sends the queries to every shard at once and merges each shard's k best,
    O(q * S k log S k); its round trip to 3 shards is in ``docs/benchmarks.md`` ("Ray: retrieval shards and the ingest farm"). Only
    the process that made the index searches through it; its threads take turns on each socket.
    :meth:`search` raises :class:`ReplicaLostError` once a shard died (actor killed, node lost,
    no answer within ``timeout``): the index cannot answer exactly without it; make a new one.
    """

    def __init__(self, smap: SprintMap, shards: int = 3, *, ship: bool = False,
                 threads: int = 1, actor_options: dict[str, Any] | None = None,
                 transport: str = "auto", timeout: float = 60.0,
                 approximate: bool = False) -> None:
        from sprint_map.fleet.runtime import require_ray

        if transport not in TRANSPORTS:
            raise ValueError(f"transport must be one of {TRANSPORTS}, not {transport!r}")
        if approximate and ship:
            raise ValueError("approximate shards search the map's own index files: they need "
                             "a shared filesystem, not shipped rows")
        self.dim = smap.config.dim
        self.approximate = approximate
        vertices = smap.stats()["vertices"]
        if approximate:
            smap.search_within(np.zeros((1, self.dim), np.float32), 1, 0)  # exact: ValueError
            self.ranges = plan_segment_ranges(smap.index_segments(), shards)
        else:
            self.ranges = plan_ranges(vertices, shards)
        ray = require_ray()
        self._ray = ray
        self.removed = smap.removed_ranges()
        remote = ray.remote(ShardWorker)
        path = str(smap.path)
        nodes = alive_nodes(ray)
        self.actors = []
        for n, (a, b) in enumerate(self.ranges):
            options = {"num_cpus": 0, "max_restarts": 0, "scheduling_strategy": spread(nodes, n),
                       **(actor_options or {})}
            rows = None
            if ship:
                rows = ray.put(np.ascontiguousarray(smap.vertex_rows(a, vertices if b is None
                                                                    else min(b, vertices))))
            self.actors.append(remote.options(**options).remote(
                None if ship else path, a, b, self.dim, rows, threads, approximate))
        self.covered: int = max(self._get([actor.covered.remote() for actor in self.actors]))
        self._lock = threading.Lock()
        self._lost: str | None = None
        self._channels: list[ChannelClient] = []
        self.transport = "ray"
        if transport != "ray":
            self._connect(transport == "socket", timeout)

    def _connect(self, required: bool, timeout: float) -> None:
        token = secrets.token_bytes(TOKEN_BYTES)
        addresses = self._get([actor.listen.remote(token) for actor in self.actors])
        try:
            for address in addresses:
                self._channels.append(ChannelClient(tuple(address), token, self.dim, timeout))
        except ChannelError:
            self._close_channels()
            if required:
                raise
            return
        self.transport = "socket"

    def _close_channels(self) -> None:
        for channel in self._channels:
            channel.close()
        self._channels = []

    def _get(self, refs: list[Any]) -> list[Any]:
        """``ray.get(refs)``, a dead actor reported as :class:`ReplicaLostError`."""
        ray = self._ray
        try:
            return list(ray.get(refs))
        except (ray.exceptions.RayActorError, ray.exceptions.ActorUnavailableError) as exc:
            raise self._lose(f"a retrieval shard died: {exc}") from exc

    def _lose(self, why: str) -> ReplicaLostError:
        self._lost = why
        self._close_channels()
        return ReplicaLostError(f"{why}; this sharded index cannot answer exactly without it: "
                                "make a new one")

    def search(self, queries: DescriptorsLike, k: int) -> SearchResult:
        """k nearest vertices, every range searched: ``(squared L2, vertex ids)``, -1 padded.
        Removed vertices included (see :meth:`search_live`)."""
        queries = np.ascontiguousarray(validate_descriptors(queries, self.dim))
        if self._lost is not None:
            raise ReplicaLostError(f"{self._lost}; make a new sharded index")
        if self.transport == "ray":
            ref = self._ray.put(queries) if queries.nbytes > 65536 else queries.tobytes()
            parts = [unpack_result(b, len(queries), k) for b in
                     self._get([actor.search_packed.remote(ref, k) for actor in self.actors])]
        else:
            with self._lock:
                try:
                    for channel in self._channels:
                        channel.send(queries, k)
                    parts = [channel.receive(len(queries), k) for channel in self._channels]
                except ChannelError as exc:
                    raise self._lose(f"a retrieval shard is lost: {exc}") from exc
        return merge_topk([p[0] for p in parts], [p[1] for p in parts], k)

    def search_live(self, queries: DescriptorsLike, k: int) -> SearchResult:
        """k nearest *live* vertices (removed sequences hidden), as ``SprintMap.search``."""
        if not self.removed.count or self.approximate:  # approximate shards hide them
            return self.search(queries, k)
        return self.removed.search_live(self.search, validate_descriptors(queries, self.dim), k,
                                        self.covered)

    def ping(self) -> None:
        """An empty round trip to every shard (on the transport searches use)."""
        if self.transport == "ray":
            self._get([actor.covered.remote() for actor in self.actors])
            return
        with self._lock:
            try:
                for channel in self._channels:
                    channel.ping()
            except ChannelError as exc:
                raise self._lose(f"a retrieval shard is lost: {exc}") from exc

    def catch_up(self, smap: SprintMap) -> int:
        """Bring the open-ended shard up to the map's committed vertices (shared filesystem),
        or ship it the new rows; refresh the removed ranges."""
        vertices = smap.stats()["vertices"]
        self.removed = smap.removed_ranges()
        tail = self.actors[-1]
        if vertices > self.covered:
            covered = self._get([tail.catch_up.remote(vertices)])[0]
            if covered < vertices:  # shipped rows: the actor cannot read the map
                covered = self._get([tail.append.remote(
                    covered, smap.vertex_rows(covered, vertices))])[0]
            self.covered = covered
        return self.covered

    def close(self) -> None:
        """End the channels and the actors."""
        self._close_channels()
        for actor in self.actors:
            self._ray.kill(actor)
        self.actors = []
