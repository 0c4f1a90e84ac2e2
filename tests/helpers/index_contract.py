"""The contract every retrieval index kind passes (zarr-python's ``StoreTests`` is the model).

:class:`IndexContract` holds the tests; a kind's test class subclasses it and says which
:class:`~sprint_map.storage.index.base.RetrievalIndex` it tests, with which config and on
how many rows (``tests/storage/test_index_contract.py``)::

    class TestFlatIndex(IndexContract):
        index_cls = FlatIndex
        config = StoreConfig(dim=DIM, index_type="flat")

Imported from the helpers package (``from tests.helpers.index_contract import
IndexContract``). Its name does not start with ``Test``, so the generic class itself is not
collected.

The data: clustered float32 rows (real descriptors cluster; an approximate index is tuned for
that) committed to a real :class:`~sprint_map.storage.shards.ShardSet` (the truth an index is
a cache of, and what the approximate kind re-ranks from); no LMDB is needed.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest

from sprint_map.storage.index.base import (
    PAD_DISTANCE,
    IndexNotLoadedError,
    RetrievalIndex,
)
from sprint_map.storage.shards import ShardSet
from sprint_map.storage.store_config import StoreConfig

__all__ = ["Committed", "IndexContract", "brute_force", "clustered"]

SHARD_ROWS = 256


def clustered(rng: np.random.Generator, n: int, centres: np.ndarray) -> np.ndarray:
    """``n`` points around ``centres`` (float32, no two equal)."""
    return (centres[rng.integers(len(centres), size=n)]
            + 0.15 * rng.standard_normal((n, centres.shape[1]))).astype(np.float32)


def brute_force(rows: np.ndarray, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The true ``k`` nearest rows of each query (squared L2, float64), ascending."""
    d = ((queries[:, None, :].astype(np.float64) - rows[None, :, :]) ** 2).sum(-1)
    ids = np.argsort(d, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(d, ids, axis=1), ids


class Committed:
    """Rows committed to a shard set, as the store's commits leave them (no LMDB)."""

    def __init__(self, directory: Path, dim: int) -> None:
        directory.mkdir(parents=True)
        self.shards = ShardSet(directory, dim, SHARD_ROWS)
        self.rows = np.empty((0, dim), dtype=np.float32)

    @property
    def total(self) -> int:
        return len(self.rows)

    def commit(self, rows: np.ndarray) -> np.ndarray:
        """Append ``rows`` to the shards; returns them as stored (float32)."""
        rows = np.ascontiguousarray(rows, dtype=np.float32)
        self.shards.append(self.total, rows)
        self.rows = np.concatenate([self.rows, rows])
        return rows


class IndexContract:
    """Tests every :class:`RetrievalIndex` kind must pass (subclass it: ``Test<Kind>``)."""

    #: The kind under test.
    index_cls: ClassVar[type[RetrievalIndex]]
    #: Its map config (dimension and the kind's parameters).
    config: ClassVar[StoreConfig]
    #: Rows of the index most tests build (at least what the kind can be built on).
    size: ClassVar[int] = 700
    #: Fewest rows :meth:`RetrievalIndex.rebuild` accepts.
    min_rows: ClassVar[int] = 0
    #: Fraction of queries (stored rows) whose own row an approximate kind must return first.
    min_self_recall: ClassVar[float] = 1.0
    #: Mean recall@10 against brute force an approximate kind must reach.
    min_recall: ClassVar[float] = 1.0

    # --- fixtures ------------------------------------------------------------------------------
    @pytest.fixture
    def centres(self, rng: np.random.Generator) -> np.ndarray:
        return rng.standard_normal((40, self.config.dim)).astype(np.float32)

    @pytest.fixture
    def data(self, tmp_path: Path) -> Committed:
        return Committed(tmp_path / "shards", self.config.dim)

    @pytest.fixture
    def directory(self, tmp_path: Path) -> Path:
        path = tmp_path / "index"
        path.mkdir()
        return path

    def make(self, directory: Path, *, writable: bool = True,
             events: list[str] | None = None) -> RetrievalIndex:
        """A new, unloaded index of the kind under test."""
        return self.index_cls(directory, self.config, writable=writable, events=events)

    @pytest.fixture
    def built(self, directory: Path, data: Committed, rng: np.random.Generator,
              centres: np.ndarray) -> Iterator[RetrievalIndex]:
        """A writer's index rebuilt (and published) on ``size`` committed rows."""
        data.commit(clustered(rng, self.size, centres))
        index = self.make(directory)
        index.rebuild(data.total, data.shards)
        yield index
        index.close()

    # --- the kind's declaration ------------------------------------------------------------------
    def test_declares_its_kind(self) -> None:
        assert isinstance(self.index_cls.kind, str) and self.index_cls.kind
        assert isinstance(self.index_cls.exact, bool)
        assert isinstance(self.index_cls.files, str) and self.index_cls.files
        if self.index_cls.exact:  # the thresholds below are an approximate kind's allowance
            assert self.min_recall == 1.0 and self.min_self_recall == 1.0

    # --- an index before load() ------------------------------------------------------------------
    def test_unloaded_on_an_empty_directory(self, directory: Path) -> None:
        index = self.make(directory)
        assert not index.loaded
        assert (index.covered, index.persisted, index.persisted_on_disk()) == (0, 0, 0)
        assert not index.has_files() and not index.published()
        assert isinstance(index.describe()["type"], str)
        assert index.discard_untrusted(0) == []
        assert index.remove_files() == []
        assert not index.persist()

    def test_search_and_add_need_load(self, directory: Path) -> None:
        index = self.make(directory)
        with pytest.raises(IndexNotLoadedError):
            index.search(np.zeros((1, self.config.dim), dtype=np.float32), 3)
        with pytest.raises(IndexNotLoadedError):
            index.add(0, np.zeros((1, self.config.dim), dtype=np.float32))

    def test_load_of_an_empty_map(self, directory: Path, data: Committed) -> None:
        """An exact index loads on nothing (and answers padding only); an approximate one
        says it cannot be loaded without a trained model."""
        index = self.make(directory)
        result = index.load(0, data.shards)
        assert result is index.loaded
        if self.index_cls.exact:
            assert result
        if index.loaded:
            distances, ids = index.search(np.zeros((2, self.config.dim), np.float32), 4)
            assert (ids == -1).all() and (distances == PAD_DISTANCE).all()
            assert index.covered == 0

    # --- search --------------------------------------------------------------------------------
    @pytest.mark.parametrize("n_queries,k", [(1, 1), (3, 10), (9, 25)])
    def test_answers_shape_dtype_and_order(self, built: RetrievalIndex, data: Committed,
                                           rng: np.random.Generator, centres: np.ndarray,
                                           n_queries: int, k: int) -> None:
        queries = clustered(rng, n_queries, centres).astype(np.float64)  # converted
        distances, ids = built.search(queries, k)
        assert distances.shape == ids.shape == (n_queries, k)
        assert distances.dtype == np.float32 and ids.dtype == np.int64
        assert ((ids >= 0) & (ids < built.covered)).all()  # fewer hits than k: none here
        assert (np.diff(distances, axis=1) >= 0).all()
        assert all(len(set(row)) == k for row in ids.tolist())

    def test_distances_are_exact_squared_l2(self, built: RetrievalIndex, data: Committed,
                                            rng: np.random.Generator,
                                            centres: np.ndarray) -> None:
        queries = clustered(rng, 6, centres)
        distances, ids = built.search(queries, 8)
        want = ((data.rows[ids] - queries[:, None, :]) ** 2).sum(-1)
        np.testing.assert_allclose(distances, want, rtol=1e-4, atol=1e-4)

    def test_nearest_neighbours(self, built: RetrievalIndex, data: Committed,
                                rng: np.random.Generator, centres: np.ndarray) -> None:
        """The exact kind returns the true nearest neighbours; an approximate one at least
        ``min_recall`` of them."""
        queries = clustered(rng, 40, centres)
        distances, ids = built.search(queries, 10)
        true_d, true_ids = brute_force(data.rows, queries, 10)
        if self.index_cls.exact:
            np.testing.assert_array_equal(ids, true_ids)
            np.testing.assert_allclose(distances, true_d, rtol=1e-4, atol=1e-4)
        recall = np.mean([len(set(a) & set(b)) / 10
                          for a, b in zip(ids.tolist(), true_ids.tolist(), strict=True)])
        assert recall >= self.min_recall

    def test_a_stored_row_finds_itself(self, built: RetrievalIndex, data: Committed) -> None:
        picks = np.arange(0, data.total, 7)
        distances, ids = built.search(data.rows[picks], 1)
        found = ids[:, 0] == picks
        assert found.mean() >= self.min_self_recall
        assert (distances[found, 0] <= 1e-4).all()

    def test_k_larger_than_the_index(self, built: RetrievalIndex, data: Committed) -> None:
        k = data.total + 50
        distances, ids = built.search(data.rows[:2], k)
        assert ids.shape == (2, k)
        for row_d, row_i in zip(distances, ids, strict=True):
            hits = int((row_i >= 0).sum())
            assert (row_i[:hits] >= 0).all() and (row_i[hits:] == -1).all()  # padding last
            assert (row_d[hits:] == PAD_DISTANCE).all() and (row_d[:hits] < PAD_DISTANCE).all()
            assert len(set(row_i[:hits].tolist())) == hits <= data.total
            if self.index_cls.exact:
                assert hits == data.total

    # --- writing -------------------------------------------------------------------------------
    def test_add_then_search_finds_the_added_rows(self, built: RetrievalIndex, data: Committed,
                                                  rng: np.random.Generator,
                                                  centres: np.ndarray) -> None:
        before = built.covered
        new = data.commit(clustered(rng, 90, centres))
        built.add(before, new[:40])
        built.add(before + 40, new[40:])
        assert built.covered == before + 90 == data.total
        distances, ids = built.search(new, 1)
        found = ids[:, 0] == np.arange(before, before + 90)
        assert found.mean() >= self.min_self_recall
        assert (distances[found, 0] <= 1e-4).all()

    def test_add_must_continue_the_covered_range(self, built: RetrievalIndex,
                                                 data: Committed) -> None:
        row = data.commit(data.rows[:1] + 1)
        for start in (built.covered - 1, built.covered + 1):
            with pytest.raises(ValueError):
                built.add(start, row)
        assert built.covered == data.total - 1

    def test_catch_up_adds_what_was_committed_without_the_index(
            self, built: RetrievalIndex, data: Committed, rng: np.random.Generator,
            centres: np.ndarray) -> None:
        before = built.covered
        data.commit(clustered(rng, 150, centres))
        built.catch_up(data.total, data.shards)
        assert built.covered == data.total
        built.catch_up(data.total, data.shards)  # nothing new: a no-op
        assert built.covered == data.total
        _, ids = built.search(data.rows[before:], 1)
        assert (ids[:, 0] == np.arange(before, data.total)).mean() >= self.min_self_recall

    def test_load_catches_up_from_the_shards(self, built: RetrievalIndex, directory: Path,
                                             data: Committed, rng: np.random.Generator,
                                             centres: np.ndarray) -> None:
        """Rows committed after the files were published: a later load covers them."""
        persisted = built.persisted_on_disk()
        files = {p.name: p.stat().st_mtime_ns for p in directory.iterdir()}
        data.commit(clustered(rng, 120, centres))
        reader = self.make(directory, writable=False)
        assert reader.load(data.total, data.shards)
        assert reader.covered == data.total and reader.persisted <= persisted
        assert not reader.persist()  # a reader ahead of the files still writes none
        assert {p.name: p.stat().st_mtime_ns for p in directory.iterdir()} == files
        _, ids = reader.search(data.rows[-120:], 1)
        assert (ids[:, 0] == np.arange(data.total - 120, data.total)).mean() >= (
            self.min_self_recall)
        reader.close()

    def test_commits_scheduled_by_after_commit_reach_the_files(
            self, built: RetrievalIndex, directory: Path, data: Committed,
            rng: np.random.Generator, centres: np.ndarray) -> None:
        """The writer's commit path: catch up, ``after_commit`` (persist when it says so),
        a final ``persist`` (close): a reader then answers like the writer."""
        for _ in range(5):
            data.commit(clustered(rng, 130, centres))
            built.catch_up(data.total, data.shards)
            due = built.after_commit(data.total, data.shards)
            assert isinstance(due, bool)
            if due:
                assert built.persist()
        built.persist()
        assert built.covered == data.total and built.persisted > self.size
        assert built.persisted_on_disk() == built.persisted
        reader = self.make(directory, writable=False)
        assert reader.load(data.total, data.shards)
        queries = clustered(rng, 15, centres)
        want, got = built.search(queries, 10), reader.search(queries, 10)
        np.testing.assert_array_equal(got[1], want[1])
        np.testing.assert_array_equal(got[0], want[0])
        reader.close()

    def test_persist_then_load_answers_the_same(self, built: RetrievalIndex, directory: Path,
                                                data: Committed, rng: np.random.Generator,
                                                centres: np.ndarray) -> None:
        data.commit(clustered(rng, 300, centres))
        built.catch_up(data.total, data.shards)
        built.persist()
        assert built.persisted_on_disk() == built.persisted > 0
        queries = clustered(rng, 20, centres)
        want = built.search(queries, 12)
        events: list[str] = []
        reader = self.make(directory, writable=False, events=events)
        assert reader.load(data.total, data.shards)
        assert reader.persisted == built.persisted and reader.covered == built.covered
        got = reader.search(queries, 12)
        np.testing.assert_array_equal(got[1], want[1])
        np.testing.assert_array_equal(got[0], want[0])
        assert events == []  # nothing discarded or rebuilt
        assert not reader.persist()  # a reader writes nothing
        reader.close()

    def test_rebuild_equals_a_fresh_build(self, built: RetrievalIndex, tmp_path: Path,
                                          data: Committed, rng: np.random.Generator,
                                          centres: np.ndarray) -> None:
        """Rebuilt in place over an older publication (more rows since), the index answers
        like one built in an empty directory, and the older publication is gone."""
        data.commit(clustered(rng, 200, centres))
        built.rebuild(data.total, data.shards)
        assert built.loaded and built.covered == data.total
        fresh_dir = tmp_path / "fresh"
        fresh_dir.mkdir()
        fresh = self.make(fresh_dir)
        fresh.rebuild(data.total, data.shards)
        queries = clustered(rng, 20, centres)
        a, b = built.search(queries, 10), fresh.search(queries, 10)
        np.testing.assert_array_equal(a[1], b[1])
        np.testing.assert_array_equal(a[0], b[0])
        assert built.persisted_on_disk() == fresh.persisted_on_disk() == built.persisted
        # only the new publication's files remain: as many as the fresh build's
        assert len(list(built.directory.iterdir())) == len(list(fresh_dir.iterdir()))
        fresh.close()

    def test_rebuild_of_a_map_too_small(self, directory: Path, data: Committed,
                                        rng: np.random.Generator, centres: np.ndarray) -> None:
        """Below ``min_rows`` a rebuild is refused and writes nothing; a kind without a
        minimum builds an empty index (and publishes no file)."""
        data.commit(clustered(rng, max(self.min_rows - 1, 0), centres))
        index = self.make(directory)
        if self.min_rows:
            with pytest.raises(ValueError):
                index.rebuild(data.total, data.shards)
            assert not index.loaded
        else:
            index.rebuild(0, data.shards)
            assert index.loaded and index.covered == 0
            assert (index.search(np.zeros((1, self.config.dim), np.float32), 2)[1] == -1).all()
        assert not index.has_files() and not any(directory.iterdir())

    # --- files ---------------------------------------------------------------------------------
    def test_published_files_describe_themselves_unloaded(self, built: RetrievalIndex,
                                                          directory: Path) -> None:
        other = self.make(directory, writable=False)
        assert other.published() and other.has_files() and not other.loaded
        assert other.persisted_on_disk() == built.persisted > 0
        # unloaded, the type is read from the files alone: a prefix of the loaded one's
        assert built.describe()["type"].startswith(other.describe()["type"].rstrip(")"))

    def test_discard_untrusted_drops_files_ahead_of_the_map(self, built: RetrievalIndex,
                                                           directory: Path) -> None:
        """The map lost commits the files saw: the writer's open drops what is ahead."""
        committed = built.persisted - 1
        opener = self.make(directory)
        actions = opener.discard_untrusted(committed)
        assert actions and all(isinstance(a, str) for a in actions)
        assert opener.persisted_on_disk() <= committed
        assert opener.discard_untrusted(committed) == []  # what is left is trusted

    def test_discard_untrusted_keeps_trusted_files(self, built: RetrievalIndex,
                                                   directory: Path) -> None:
        before = sorted(p.name for p in directory.iterdir())
        assert self.make(directory).discard_untrusted(built.covered) == []
        assert sorted(p.name for p in directory.iterdir()) == before

    def test_remove_files_leaves_the_loaded_index(self, built: RetrievalIndex,
                                                  directory: Path, data: Committed) -> None:
        want = built.search(data.rows[:3], 5)
        removed = built.remove_files()
        assert removed and not built.has_files() and not built.published()
        assert not any(directory.iterdir())
        got = built.search(data.rows[:3], 5)
        np.testing.assert_array_equal(got[1], want[1])

    def test_loading_skips_a_torn_file(self, built: RetrievalIndex, directory: Path,
                                       data: Committed) -> None:
        """The published file of the highest vertex ids cut short: a reader's load still
        covers every row (from the shards), reporting what it left out."""
        path = sorted(directory.glob("*.faiss"))[-1]
        with open(path, "r+b") as fh:
            fh.truncate(path.stat().st_size - 8)
        events: list[str] = []
        reader = self.make(directory, writable=False, events=events)
        assert reader.load(data.total, data.shards)
        assert reader.covered == data.total and events
        assert reader.persisted < built.persisted
        _, ids = reader.search(data.rows, 1)
        assert (ids[:, 0] == np.arange(data.total)).mean() >= self.min_self_recall
        assert path.exists()  # a reader deletes nothing
        reader.close()

    # --- lifetime ------------------------------------------------------------------------------
    def test_close_is_idempotent_and_load_reopens(self, built: RetrievalIndex,
                                                  data: Committed) -> None:
        want = built.search(data.rows[:4], 6)
        built.close()
        built.close()
        assert not built.loaded and built.covered == 0
        with pytest.raises(IndexNotLoadedError):
            built.search(data.rows[:4], 6)
        assert built.load(data.total, data.shards)
        got = built.search(data.rows[:4], 6)
        np.testing.assert_array_equal(got[1], want[1])

    def test_an_unloaded_reader_changes_no_file(self, built: RetrievalIndex, directory: Path,
                                                data: Committed) -> None:
        before = {p.name: p.stat().st_mtime_ns for p in directory.iterdir()}
        reader = self.make(directory, writable=False)
        assert reader.load(data.total, data.shards)
        assert not reader.persist()
        reader.close()
        assert {p.name: p.stat().st_mtime_ns for p in directory.iterdir()} == before
