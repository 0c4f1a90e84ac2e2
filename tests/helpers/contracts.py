"""Contract suites: the tests every implementation of one interface passes.

Each class holds the tests of one contract; an implementation's test class subclasses it and
supplies the hooks the contract names (zarr-python's ``StoreTests`` is the model; the
retrieval indexes have theirs in :mod:`tests.helpers.index_contract`). The class names do not
start with ``Test``, so pytest collects only the subclasses:

- :class:`GraphSourceContract`: where the HMM's components come from (memory, LMDB);
- :class:`ComponentCacheContract`: the HMM's byte-bounded LRU caches of components;
- :class:`RowWriterContract`: writers of uncommitted rows (one sequence, a group of them);
- :class:`ExporterContract`: the map's exports (GraphML at each level, CSV, GeoJSON);
- :class:`FrameSourceContract`: frame sources (image directories, videos, ``.npy``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import pytest

from sprint_map.errors import InputError, SprintMapError, StorageIOError
from sprint_map.export.report import ExportReport
from sprint_map.frontend.sources import FrameSource
from sprint_map.hmm.cache import ComponentCache
from sprint_map.hmm.graph import ComponentGraph, GraphSource
from sprint_map.map import SprintMap
from sprint_map.storage.store import MapStore

#: ``(src vertex, dst vertex, weight)``: a directed inter-sequence edge by global vertex ids.
Edge = tuple[int, int, float]


# --- graph sources ----------------------------------------------------------------------------
class GraphSourceContract:
    """A :class:`~sprint_map.hmm.graph.GraphSource` over sequences of ``lengths`` (vertex ids
    assigned in order from 0, as the map does) and directed ``edges``: ``components_of`` groups
    vertices by the connected sequences, ``load_component`` gives their compact arrays.

    Hook: ``make(tmp_path, lengths, edges) -> (source, seq_ids)``, ``seq_ids[i]`` the id the
    source gives sequence ``i``.
    """

    #: Sequences 0-2 joined by edges (both directions), 3 alone, 4-5 joined one way.
    LENGTHS: ClassVar[tuple[int, ...]] = (5, 7, 3, 4, 6, 2)
    EDGES: ClassVar[tuple[Edge, ...]] = ((6, 1, 0.5), (12, 3, 0.25), (2, 13, 1.0),
                                         (25, 20, 0.75))
    GROUPS: ClassVar[tuple[tuple[int, ...], ...]] = ((0, 1, 2), (3,), (4, 5))

    def make(self, tmp_path: Path, lengths: Sequence[int], edges: Sequence[Edge]
             ) -> tuple[GraphSource, list[int]]:
        raise NotImplementedError

    @pytest.fixture
    def built(self, tmp_path: Path) -> tuple[GraphSource, list[int]]:
        return self.make(tmp_path, self.LENGTHS, self.EDGES)

    def first(self, seq: int) -> int:
        return sum(self.LENGTHS[:seq])

    def test_components_of_groups_every_vertex_by_its_connected_sequences(self, built):
        source, _ = built
        comps = source.components_of(np.arange(sum(self.LENGTHS), dtype=np.int64))
        by_seq = np.repeat(np.arange(len(self.LENGTHS)), self.LENGTHS)
        ids = [{int(c) for c in comps[np.isin(by_seq, group)]} for group in self.GROUPS]
        assert all(len(i) == 1 for i in ids), ids
        assert len(set.union(*ids)) == len(self.GROUPS)

    def test_components_of_answers_one_vertex_and_repeats(self, built):
        source, _ = built
        one = source.components_of(np.array([9], dtype=np.int64))
        many = source.components_of(np.array([9, 0, 9, 14], dtype=np.int64))
        assert one.shape == (1,) and many.tolist() == [one[0], one[0], one[0], many[3]]

    def test_sequence_first_names_each_vertex_sequence(self, built):
        """The drive rival's look-up (``HMMConfig.rival_reach``): the first vertex id of each
        vertex's sequence."""
        source, _ = built
        ids = np.arange(sum(self.LENGTHS), dtype=np.int64)[::-1].copy()
        want = np.repeat([self.first(s) for s in range(len(self.LENGTHS))], self.LENGTHS)[::-1]
        assert source.sequence_first(ids).tolist() == want.tolist()

    def test_load_component_gives_its_sequences_and_edges(self, built):
        source, seq_ids = built
        for group in self.GROUPS:
            cid = int(source.components_of(np.array([self.first(group[0])]))[0])
            graph: ComponentGraph = source.load_component(cid)
            assert graph.component_id == cid
            assert graph.seq_ids.tolist() == sorted(seq_ids[s] for s in group)
            order = sorted(group, key=lambda s: seq_ids[s])
            assert graph.seq_first.tolist() == [self.first(s) for s in order]
            assert graph.seq_len.tolist() == [self.LENGTHS[s] for s in order]
            assert graph.n_vertices == sum(self.LENGTHS[s] for s in group)
            inside = {(a, b, w) for a, b, w in self.EDGES
                      if self.first(group[0]) <= a < self.first(group[-1] + 1)}
            got = set(zip(graph.edge_src.tolist(), graph.edge_dst.tolist(),
                          graph.edge_weight.tolist(), strict=True))
            assert got == inside

    def test_a_vertex_outside_the_map_is_refused(self, built):
        source, _ = built
        for vid in (-1, sum(self.LENGTHS)):
            with pytest.raises(ValueError):
                source.components_of(np.array([vid], dtype=np.int64))


# --- component caches -------------------------------------------------------------------------
class ComponentCacheContract:
    """A :class:`~sprint_map.hmm.cache.ComponentCache`: ``get`` loads on a miss only, keeps
    the least recently used components within its byte budget, never keeps one larger than
    the budget, forgets on ``invalidate``/``clear``, and refuses a loader's wrong component.

    Hook: ``cache_cls``.
    """

    cache_cls: ClassVar[type[ComponentCache]]

    @staticmethod
    def component(cid: int, length: int = 10) -> ComponentGraph:
        return ComponentGraph(component_id=cid, seq_ids=np.array([cid]),
                              seq_first=np.array([cid * 1000]), seq_len=np.array([length]),
                              edge_src=np.zeros(0, np.int64), edge_dst=np.zeros(0, np.int64),
                              edge_weight=np.zeros(0))

    @pytest.fixture
    def loads(self) -> list[int]:
        return []

    @pytest.fixture
    def loader(self, loads: list[int]) -> Callable[[int], ComponentGraph]:
        def load(cid: int) -> ComponentGraph:
            loads.append(cid)
            return self.component(cid)
        return load

    def test_a_miss_loads_and_a_hit_does_not(self, loader, loads):
        cache = self.cache_cls(1 << 20)
        first = cache.get(1, loader)
        assert cache.get(1, loader) is first
        assert loads == [1] and (cache.hits, cache.misses) == (1, 1)
        assert 1 in cache and len(cache) == 1 and cache.nbytes == first.nbytes

    def test_the_least_recently_used_goes_first_within_the_budget(self, loader, loads):
        size = self.component(0).nbytes
        cache = self.cache_cls(2 * size)
        cache.get(1, loader), cache.get(2, loader), cache.get(1, loader)  # 2 is now the LRU
        cache.get(3, loader)
        assert 2 not in cache and 1 in cache and 3 in cache and cache.nbytes <= 2 * size
        cache.get(2, loader)
        assert loads == [1, 2, 3, 2]

    def test_a_component_over_the_budget_is_returned_not_kept(self, loader):
        cache = self.cache_cls(self.component(0).nbytes - 1)
        assert cache.get(5, loader).component_id == 5
        assert 5 not in cache and cache.nbytes == 0

    def test_invalidate_and_clear_forget(self, loader, loads):
        cache = self.cache_cls(1 << 20)
        for cid in (1, 2, 3):
            cache.get(cid, loader)
        cache.invalidate([2, 99])
        assert 2 not in cache and len(cache) == 2
        cache.get(2, loader)
        assert loads == [1, 2, 3, 2]
        cache.clear()
        assert len(cache) == 0 and cache.nbytes == 0

    def test_a_loader_returning_another_component_is_refused(self):
        cache = self.cache_cls(1 << 20)
        with pytest.raises(ValueError, match="loader returned component 2 for 1"):
            cache.get(1, lambda cid: self.component(2))
        assert 1 not in cache and 2 not in cache

    def test_a_negative_budget_is_refused(self):
        with pytest.raises(ValueError):
            self.cache_cls(-1)


# --- row writers ------------------------------------------------------------------------------
class RowWriterContract:
    """A writer of uncommitted rows (:class:`~sprint_map.storage.sequence_writer.UncommittedRows`):
    its rows are invisible until its commit, read back bit for bit after it, and dropped by an
    abort, by leaving its ``with`` block without a commit or by an error (which propagates);
    it holds the map's writing slot meanwhile, and is done after a commit or an abort.

    Hooks: ``begin(store, name)`` -> the writer of a sequence ``name``; ``write(writer,
    rows)``; ``commit(writer)`` -> the sequences' ``AddResult`` list.
    """

    DIM: ClassVar[int] = 8

    def begin(self, store: MapStore, name: str) -> Any:
        raise NotImplementedError

    def write(self, writer: Any, rows: np.ndarray) -> None:
        raise NotImplementedError

    def commit(self, writer: Any) -> list[Any]:
        raise NotImplementedError

    @pytest.fixture
    def store(self, tmp_path: Path, rng: np.random.Generator) -> Any:
        from sprint_map.config import MapConfig, StoreOptions

        config = MapConfig(dim=self.DIM, store=StoreOptions(shard_rows=16))
        store = MapStore.create(tmp_path / "m", config)
        store.add_sequence(rng.standard_normal((10, self.DIM)).astype(np.float32), name="base")
        yield store
        store.close()

    def rows(self, rng: np.random.Generator, n: int = 23) -> np.ndarray:
        return rng.standard_normal((n, self.DIM)).astype(np.float32)

    def test_committed_rows_read_back_bit_for_bit(self, store, rng):
        rows = self.rows(rng)
        writer = self.begin(store, "new")
        with writer:
            self.write(writer, rows)
            assert store.stats()["vertices"] == 10  # invisible before the commit
            (result,) = self.commit(writer)
        assert result.sequence.name == "new" and result.sequence.first_vertex == 10
        np.testing.assert_array_equal(store.descriptors(result.sequence.seq_id), rows)
        assert store.stats()["vertices"] == 10 + len(rows)

    def test_leaving_without_a_commit_drops_the_rows(self, store, rng):
        with self.begin(store, "dropped") as writer:
            self.write(writer, self.rows(rng))
        assert store.stats() == {"sequences": 1, "vertices": 10, "edges": 0, "components": 1}
        assert store.writing is None
        rows = self.rows(rng, 5)
        (result,) = self.commit_one(store, rows, "next")  # the slot is free, the ids reused
        assert result.sequence.first_vertex == 10
        np.testing.assert_array_equal(store.descriptors(result.sequence.seq_id), rows)

    def test_an_error_aborts_and_propagates(self, store, rng):
        with pytest.raises(RuntimeError, match="boom"), self.begin(store, "failed") as writer:
            self.write(writer, self.rows(rng))
            raise RuntimeError("boom")
        assert store.stats()["vertices"] == 10 and store.writing is None

    def test_one_writer_at_a_time(self, store, rng):
        with self.begin(store, "only") as writer:
            with pytest.raises(SprintMapError, match="already being written"):
                self.begin(store, "second")
            self.write(writer, self.rows(rng))
            self.commit(writer)
        assert store.writing is None

    def test_done_after_an_abort(self, store, rng):
        writer = self.begin(store, "aborted")
        self.write(writer, self.rows(rng))
        writer.abort()
        writer.abort()  # once: later calls do nothing
        with pytest.raises(SprintMapError):
            self.commit(writer)
        assert store.stats()["vertices"] == 10

    def commit_one(self, store: MapStore, rows: np.ndarray, name: str) -> list[Any]:
        with self.begin(store, name) as writer:
            self.write(writer, rows)
            return self.commit(writer)


# --- exporters --------------------------------------------------------------------------------
class ExporterContract:
    """One export of a map (``small_map``, ``tests/export/conftest.py``): it reports what it
    wrote (its size on disk, its live sequences, the nodes and edges a reader of the file
    finds), publishes atomically (no ``*.partial`` left; a failure mid-write leaves the
    previous file whole), and refuses a target it cannot write.

    Hooks: ``export(smap, target) -> ExportReport``; ``target(tmp_path)``; ``bad_target``;
    ``read(report) -> (nodes, edges)`` from the written file(s); ``writer``: the name
    (module attribute of :mod:`sprint_map.export`) of the function that writes the content,
    for the failure test.
    """

    writer: ClassVar[str]

    def export(self, smap: SprintMap, target: Path) -> ExportReport:
        raise NotImplementedError

    def target(self, tmp_path: Path) -> Path:
        raise NotImplementedError

    def read(self, report: ExportReport) -> tuple[int, int]:
        raise NotImplementedError

    def files(self, report: ExportReport) -> list[Path]:
        return [Path(f) for f in report.files] or [Path(report.path)]

    def test_the_report_says_what_was_written(self, small_map, tmp_path):
        with SprintMap.open(small_map, readonly=True) as m:
            report = self.export(m, self.target(tmp_path))
            live = len(m.sequences())
        assert report.sequences == live
        assert report.bytes == sum(f.stat().st_size for f in self.files(report))
        assert self.read(report) == (report.nodes, report.edges)
        assert not list(tmp_path.rglob("*.partial"))

    def test_a_failed_export_leaves_the_previous_file_whole(self, small_map, tmp_path,
                                                            monkeypatch):
        import sprint_map.export as export

        with SprintMap.open(small_map, readonly=True) as m:
            first = self.export(m, self.target(tmp_path))
            before = {f: f.read_bytes() for f in self.files(first)}

            def fail(*args: Any, **kwargs: Any) -> Any:
                raise OSError(28, "No space left on device")

            monkeypatch.setattr(export, self.writer, fail)
            with pytest.raises(StorageIOError, match="No space"):
                self.export(m, self.target(tmp_path))
        assert {f: f.read_bytes() for f in before} == before
        assert not list(tmp_path.rglob("*.partial"))

    def bad_target(self, tmp_path: Path) -> Path:
        """A target the export must refuse: by default a directory where a file is due."""
        return tmp_path

    def test_an_unwritable_target_is_refused(self, small_map, tmp_path):
        with SprintMap.open(small_map, readonly=True) as m, pytest.raises(InputError):
            self.export(m, self.bad_target(tmp_path))


# --- frame sources ----------------------------------------------------------------------------
class FrameSourceContract:
    """A :class:`~sprint_map.frontend.sources.FrameSource` of ``FRAMES`` frames: it names its
    kind, count and dimension, yields float32 C-contiguous batches of ``batch_size`` rows (the
    last one shorter), keeps every ``stride``-th frame, reports progress after each batch, and
    lets its consumer stop early; ``read_all`` is its batches concatenated.

    Hooks: ``kind``; ``make(tmp_path) -> path`` of a source of ``FRAMES`` frames; ``spec``
    (None: the source's default).
    """

    FRAMES: ClassVar[int] = 11
    kind: ClassVar[str]
    spec: ClassVar[Any] = None

    def make(self, tmp_path: Path) -> Path:
        raise NotImplementedError

    def open(self, path: Path, **kwargs: Any) -> FrameSource:
        from sprint_map.frontend import open_source

        return open_source(path, self.spec, workers=kwargs.pop("workers", 2), **kwargs)

    @pytest.fixture
    def path(self, tmp_path: Path) -> Path:
        return self.make(tmp_path)

    def test_it_names_its_kind_count_and_dimension(self, path):
        source = self.open(path)
        assert source.kind == self.kind and source.name == path.stem
        assert source.count in (self.FRAMES, None)
        assert source.read_all().shape == (self.FRAMES, source.dim)

    @pytest.mark.parametrize("batch_size", [1, 4, 256])
    def test_batches_are_float32_rows_in_frame_order(self, path, batch_size):
        batches = list(self.open(path, batch_size=batch_size).iter_batches())
        assert all(len(b) == batch_size for b in batches[:-1])
        assert 1 <= len(batches[-1]) <= batch_size
        assert all(b.dtype == np.float32 and b.flags.c_contiguous for b in batches)
        np.testing.assert_array_equal(np.concatenate(batches), self.open(path).read_all())

    def test_stride_keeps_every_nth_frame(self, path):
        every = self.open(path).read_all()
        source = self.open(path, stride=3)
        assert source.count in (math.ceil(self.FRAMES / 3), None)
        np.testing.assert_array_equal(source.read_all(), every[::3])

    def test_progress_after_each_batch(self, path):
        calls: list[tuple[int, int | None]] = []
        self.open(path, batch_size=4, progress=lambda d, t: calls.append((d, t))).read_all()
        assert [d for d, _ in calls] == [4, 8, self.FRAMES]
        assert all(t in (self.FRAMES, None) for _, t in calls)

    def test_the_consumer_may_stop_early(self, path):
        for batch in self.open(path, batch_size=2).iter_batches():
            assert len(batch) == 2
            break
        assert self.open(path).read_all().shape[0] == self.FRAMES  # nothing left locked
