"""A reader's consistent view of the map: one LMDB read transaction and what it implies.

Readers run beside the writer (``docs/architecture.md``, "Concurrency"). A reader that reads
the map in several transactions can mix two states of it: a search that returns a vertex the
writer committed a moment later than the component look-up that follows it, or a vertex whose
sequence a ``remove`` retired in between. A :class:`MapSnapshot` pins one LMDB read transaction
and everything derived from it (the vertex count, the removed ranges) so that every read a
whole ``localize`` makes sees the same map:

- :meth:`MapSnapshot.search` asks the shared in-memory index (which may cover vertices committed
  after the snapshot: another snapshot of this process caught it up) and keeps only the hits
  the snapshot holds: ids below its vertex count and outside its removed ranges;
- :attr:`MapSnapshot.txn` is handed to every other read (sequences, vertex ranges, union-find,
  edges), so they answer as of the same commit.

Shard rows are append-only and a reader's generation is pinned (``storage/generation.py``), so
the rows of the snapshot's vertices stay readable for as long as it is held. Holding a snapshot
pins LMDB pages like any read transaction: the writer's file grows meanwhile, by what it commits
while the snapshot is held.
"""

from __future__ import annotations

from contextlib import ExitStack, suppress
from typing import TYPE_CHECKING, Any

import lmdb
import numpy as np

from sprint_map.storage.removal import RemovedRanges, search_live
from sprint_map.util.arrays import DescriptorsLike, SearchResult
from sprint_map.util.validation import validate_descriptors

if TYPE_CHECKING:
    from sprint_map.storage.store import MapStore


class MapSnapshot:
    """The map as of one LMDB read transaction; a context manager.

    Attributes
    ----------
    txn : lmdb.Transaction
        The read transaction; pass it to the store's readers (``locate``, ``sequence``, ...).
    version : int
        LMDB's id of the last write transaction this snapshot sees: two snapshots with the
        same version see the same map.
    vertices : int
        ``next_vertex_id`` as of the snapshot: vertex ids ``0..vertices-1`` exist in it.
    removed : RemovedRanges
        The removed vertex ranges as of the snapshot.

    Notes
    -----
    Opening is O(1) (two meta reads) when the removed ranges are cached, else O(removed
    sequences). Not for use by two threads at once (an LMDB read transaction is not).
    """

    def __init__(self, store: MapStore) -> None:
        self.store = store
        self._stack = ExitStack()
        self.txn: lmdb.Transaction = self._stack.enter_context(store.env.read())
        try:
            self.version = int(self.txn.id())
            self.vertices = store.counter("next_vertex_id", self.txn)
            self.removed: RemovedRanges = store.removed_ranges(self.txn)
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        """Release the read transaction. Idempotent."""
        with suppress(lmdb.Error):  # the environment was closed first: the txn is gone
            self._stack.close()

    def __enter__(self) -> MapSnapshot:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def search(self, queries: DescriptorsLike, k: int) -> SearchResult:
        """k nearest vertices of this snapshot: ``(squared L2 distances, vertex ids)``.

        Rows are -1 padded (distance ``float32`` max) like FAISS pads them. Hits past the
        snapshot's vertex count or in its removed ranges are dropped and the index asked for
        more candidates (:func:`~sprint_map.storage.removal.search_live`).

        Notes
        -----
        The in-memory index is first caught up to the newest commit (one meta read): a
        persisted index file newer than the snapshot is then still trusted rather than rebuilt
        from the shards, and snapshots of one process share one index.
        """
        store = self.store
        queries = validate_descriptors(queries, store.config.dim)
        latest = max(store.counter("next_vertex_id"), self.vertices)
        store.index.load(latest, store.shards)
        indexed = int(store.index.covered)
        hidden = self.removed
        if indexed > self.vertices:  # committed after this snapshot: hidden like removed ones
            hidden = RemovedRanges(np.append(hidden.first, self.vertices),
                                   np.append(hidden.last, indexed - 1),
                                   np.append(hidden.seq_ids, -1))
        if not hidden.count:
            return store.index.search(queries, k)
        return search_live(store.index.search, queries, k, hidden, indexed)

    def locate(self, vertex_ids: Any) -> list[tuple[int, int]]:
        """``(seq_id, image_id)`` of each vertex id, as of this snapshot."""
        return self.store.locate(vertex_ids, self.txn)


__all__ = ["MapSnapshot"]
