"""Learning the map's descriptor projection from its merged edges (``index --learn``).

The edges are storage records: each joins two vertices, whose shard rows are two views of one
place. :func:`learn` reads them (each undirected pair once), a seeded sample of the map's rows,
fits a projection (:func:`~sprint_map.storage.index.projection.learn_projection`: adopted only
if it retrieves held-back pairs better than the plain descriptor) and installs it with an
index rebuilt under it (:meth:`~sprint_map.storage.index.map_index.IndexStore.install`, crash
safe). The raw rows stay in the shards: a projection can always be retrained or dropped.

The writer retrains by itself after ``learn_every`` new edges (counted like ``info``'s
``edges``; 0, the default, never): :func:`due`. The map records every attempt's edge count in
the pointer, adopted or not, so a refused attempt is not repeated at every commit.
"""

from __future__ import annotations

from typing import Protocol

import lmdb
import numpy as np

from sprint_map.storage.index.map_index import IndexStore
from sprint_map.storage.index.model import gather_rows, sample_ids
from sprint_map.storage.index.projection import ROW_SAMPLE, Learned, LearnReport, learn_projection
from sprint_map.storage.keys import EDGE_KEY
from sprint_map.storage.lmdb_env import LmdbEnv
from sprint_map.storage.shards import ShardSet
from sprint_map.storage.store_config import StoreConfig
from sprint_map.util.arrays import Int64Array


class LearningMap(Protocol):
    """What learning uses of a map open for writing (``MapStore`` is one)."""

    @property
    def env(self) -> LmdbEnv: ...

    @property
    def config(self) -> StoreConfig: ...

    @property
    def shards(self) -> ShardSet: ...

    @property
    def index(self) -> IndexStore: ...

    def require_writer(self) -> None: ...

    def counter(self, name: str, txn: lmdb.Transaction | None = None) -> int: ...


__all__ = ["PAIR_SAMPLE", "LearningMap", "due", "learn", "merged_pairs", "unlearn"]

#: Pairs a projection is fitted on at most (a seeded sample of the edges beyond that).
PAIR_SAMPLE = 200_000


def merged_pairs(store: LearningMap) -> tuple[Int64Array, Int64Array, int, int]:
    """``(a, b, n_edges, committed)``: every edge's endpoints once (``a < b``), sorted by
    ``a``, as of one snapshot, with the edge counter and vertex count of that snapshot.
    O(E) keys read (values are not)."""
    with store.env.read() as txn:
        n_edges = store.counter("n_edges", txn)
        committed = store.counter("next_vertex_id", txn)
        cursor = txn.cursor(db=store.env.db("edges"))
        raw = b"".join(cursor.iternext(keys=True, values=False))
    keys = np.frombuffer(raw[: len(raw) - len(raw) % EDGE_KEY.size], dtype=">u8").astype(
        np.int64).reshape(-1, 2)
    a, b = np.minimum(keys[:, 0], keys[:, 1]), np.maximum(keys[:, 0], keys[:, 1])
    pairs = np.unique(np.stack([a, b], axis=1), axis=0) if len(a) else np.empty((0, 2), np.int64)
    return pairs[:, 0].copy(), pairs[:, 1].copy(), n_edges, committed


def learn(store: LearningMap) -> LearnReport:
    """Learn a projection from the map's merged edges and adopt it if it helps (writer).

    Notes
    -----
    O(E) edge keys, O(min(E, PAIR_SAMPLE) + ROW_SAMPLE) rows gathered, the fit (see
    ``learn_projection``), and when adopted an index rebuild (O(N * dim_in * dim_out) to
    project the map plus the index's own build).
    """
    store.require_writer()
    cfg = store.config
    a, b, n_edges, committed = merged_pairs(store)
    if len(a) > PAIR_SAMPLE:  # a seeded sample, kept in vertex order (held-back blocks)
        keep = np.sort(np.random.default_rng(n_edges).choice(len(a), PAIR_SAMPLE,
                                                              replace=False))
        a, b = a[keep], b[keep]
    rows = gather_rows(store.shards, sample_ids(committed, ROW_SAMPLE, 0), committed)
    report, projection = learn_projection(
        rows, gather_rows(store.shards, a, committed), gather_rows(store.shards, b, committed),
        a, b, dim_out=cfg.learn_dim, min_pairs=cfg.learn_min_pairs)
    if projection is None:  # refused: the projection in use (if any) stays
        store.index.record_attempt(n_edges)
        return report
    record = Learned(attempted_at_edges=n_edges, pairs=report.pairs, trained_at_edges=n_edges,
                     heldout_recall_before=report.heldout_recall_before,
                     heldout_recall_after=report.heldout_recall_after)
    store.index.install(record, projection, committed, store.shards)
    return report


def unlearn(store: LearningMap) -> bool:
    """Drop the learned projection (the plain descriptor again); False if there was none."""
    store.require_writer()
    current = store.index.learned_state()
    with store.env.read() as txn:
        committed = store.counter("next_vertex_id", txn)
        n_edges = store.counter("n_edges", txn)
    store.index.install(Learned(attempted_at_edges=max(current.attempted_at_edges, n_edges)),
                        None, committed, store.shards)
    return bool(current.generation)


def due(store: LearningMap) -> bool:
    """Whether ``learn_every`` new edges were committed since the last attempt. O(1) reads."""
    every = store.config.learn_every
    if not every:
        return False
    return store.counter("n_edges") - store.index.learned_state().attempted_at_edges >= every
