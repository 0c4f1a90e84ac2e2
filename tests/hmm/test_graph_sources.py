"""Every graph source passes the one contract (:class:`tests.helpers.contracts.GraphSourceContract`):
the HMM's in-memory source and the map's LMDB one give the same components."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from sprint_map.config import MapConfig
from sprint_map.hmm.graph import MemoryGraphSource
from sprint_map.localize.stored_view import StoredMapView
from sprint_map.storage.records import EdgeSpec
from sprint_map.storage.store import MapStore
from sprint_map.storage.store_config import StoreOptions
from tests.helpers.contracts import Edge, GraphSourceContract


class TestMemoryGraphSource(GraphSourceContract):
    def make(self, tmp_path: Path, lengths: Sequence[int], edges: Sequence[Edge]):
        return MemoryGraphSource(lengths, edges), list(range(len(lengths)))


class TestStoredMapView(GraphSourceContract):
    """The LMDB source over a map whose sequences were committed with these edges (each edge
    committed with the later of its two sequences, as a merge does)."""

    def make(self, tmp_path: Path, lengths: Sequence[int], edges: Sequence[Edge]):
        firsts = np.concatenate([[0], np.cumsum(lengths)])
        rng = np.random.default_rng(0)
        store = MapStore.create(tmp_path / "m", MapConfig(dim=4, store=StoreOptions(shard_rows=8)))
        seq_ids = []
        for s, length in enumerate(lengths):
            def end(vertex: int, s: int = s) -> tuple[int | None, int]:
                seq = int(np.searchsorted(firsts, vertex, side="right") - 1)
                return (None if seq == s else seq_ids[seq], vertex - int(firsts[seq]))

            mine = [EdgeSpec(end(a), end(b), w) for a, b, w in edges
                    if max(np.searchsorted(firsts, [a, b], side="right") - 1) == s]
            result = store.add_sequence(rng.standard_normal((length, 4)).astype(np.float32),
                                        edges=mine)
            seq_ids.append(result.sequence.seq_id)
        return StoredMapView(store), seq_ids

    def test_sequence_first_pinned_reads_the_known_ranges(self, tmp_path: Path):
        source, _ = self.make(tmp_path, self.LENGTHS, self.EDGES)
        ids = np.array([14, 0, 5, 11, 26, 20], dtype=np.int64)
        with source.pinned():
            assert source.sequence_first(ids).tolist() == [12, 0, 5, 5, 25, 19]
            assert source.sequence_first(ids[:2]).tolist() == [12, 0]  # from memory now
