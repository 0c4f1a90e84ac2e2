"""IndexStore: one active index, its kind chosen by the config and the map's size; switching
kind replaces it and removes the other kind's files after the new ones are published."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from sprint_map.storage.index.flat import FlatIndex, index_files
from sprint_map.storage.index.manifest import MANIFEST
from sprint_map.storage.index.map_index import KINDS, IndexStore
from sprint_map.storage.index.segmented import SegmentedIndex
from sprint_map.storage.store_config import StoreConfig
from tests.helpers.index_contract import Committed, clustered

DIM = 32
#: auto switches to ivf-pq at 1000 * 128 / 32 = 4000 vertices of dim 32.
AUTO = StoreConfig(dim=DIM, index_type="auto", index_auto_vertices=1000, index_nlist=16,
                 index_nprobe=8, index_segment_rows=256, index_merge_factor=3,
                 index_train_sample=2000, index_rerank=50, index_persist_every=100)


@pytest.fixture
def data(tmp_path: Path) -> Committed:
    return Committed(tmp_path / "shards", DIM)


@pytest.fixture
def directory(tmp_path: Path) -> Path:
    (tmp_path / "index").mkdir()
    return tmp_path / "index"


@pytest.fixture
def centres(rng: np.random.Generator) -> np.ndarray:
    return rng.standard_normal((40, DIM)).astype(np.float32)


def store(directory: Path, config: StoreConfig = AUTO, writable: bool = True) -> IndexStore:
    return IndexStore(directory, DIM, writable=writable, config=config)


def test_kinds_are_ordered_by_precedence() -> None:
    assert (FlatIndex, SegmentedIndex) == KINDS


def test_nothing_loaded_is_an_unloaded_flat_index(directory: Path) -> None:
    index = store(directory)
    assert isinstance(index.active, FlatIndex) and index.index is None
    assert index.describe() == {"type": "IndexIDMap2(IndexFlatL2)"}
    assert (index.covered, index.persisted, index.persisted_on_disk()) == (0, 0, 0)
    assert not index.has_files()


def test_the_map_switches_kind_when_it_grows(directory: Path, data: Committed,
                                             rng: np.random.Generator,
                                             centres: np.ndarray) -> None:
    index = store(directory)
    first = 0
    for _ in range(4):  # 3000 vertices: flat, persisted on the schedule
        data.commit(clustered(rng, 750, centres))
        if index.after_commit(data.total, data.shards, first):
            index.persist()
        first = data.total
    assert isinstance(index.active, FlatIndex) and index.active.loaded
    flat = index.active
    assert index_files(directory) and not (directory / MANIFEST).exists()
    data.commit(clustered(rng, 1200, centres))  # 4200: past the threshold
    assert not index.after_commit(data.total, data.shards, first)
    assert isinstance(index.active, SegmentedIndex) and index.covered == data.total
    assert not flat.loaded  # the replaced index was closed
    assert not index_files(directory)  # the flat files went once the segments were named
    assert any("index trained" in event for event in index.events)
    _, ids = index.search(data.rows[::97], 1)
    np.testing.assert_array_equal(ids[:, 0], np.arange(0, data.total, 97))
    index.close()
    assert index.index is None and isinstance(index.active, FlatIndex)
    # unloaded, it describes what is published
    assert index.describe()["type"].startswith("segmented ivf-pq")
    assert index.persisted_on_disk() == 4096


def test_a_writer_open_removes_flat_files_a_publication_superseded(
        directory: Path, data: Committed, rng: np.random.Generator,
        centres: np.ndarray) -> None:
    """Killed between publishing the segments and removing the flat file: the next writer's
    open removes the flat file, which the segments supersede."""
    data.commit(clustered(rng, 600, centres))
    flat = FlatIndex(directory, AUTO, writable=True)
    flat.rebuild(data.total, data.shards)
    segmented = SegmentedIndex(directory, AUTO, writable=True)
    segmented.rebuild(data.total, data.shards)
    segmented.close()
    name = index_files(directory)[0][1].name
    actions = store(directory).discard_untrusted(data.total)
    assert actions == [f"removed index {name}: superseded by the segments"]
    assert not index_files(directory) and (directory / MANIFEST).exists()
    reader = store(directory, writable=False)
    reader.load(data.total, data.shards)
    assert isinstance(reader.active, SegmentedIndex) and reader.covered == data.total


def test_a_flat_config_never_opens_segments(directory: Path, data: Committed,
                                            rng: np.random.Generator,
                                            centres: np.ndarray) -> None:
    data.commit(clustered(rng, 600, centres))
    segmented = SegmentedIndex(directory, AUTO, writable=True)
    segmented.rebuild(data.total, data.shards)
    segmented.close()
    index = store(directory, StoreConfig(dim=DIM, index_type="flat"), writable=False)
    index.load(data.total, data.shards)
    assert isinstance(index.active, FlatIndex) and index.covered == data.total


def test_train_on_a_map_too_small_rebuilds_flat_and_drops_segments(
        directory: Path, data: Committed, rng: np.random.Generator,
        centres: np.ndarray) -> None:
    config = replace(AUTO, index_type="ivf-pq")
    data.commit(clustered(rng, 600, centres))
    index = store(directory, config)
    index.load(data.total, data.shards)  # ivf-pq and 600 >= MIN_TRAIN: trained on load
    assert isinstance(index.active, SegmentedIndex)
    small = store(directory, config)
    lines = small.train(200, data.shards)  # as if the map had 200 vertices
    assert lines == ["rebuilt the flat index (200 vertices)"]
    assert isinstance(small.active, FlatIndex) and small.covered == 200
    assert not (directory / MANIFEST).exists()
    assert [upto for upto, _ in index_files(directory)] == [200]


def test_a_reader_far_behind_the_writer_reopens_the_segments(
        directory: Path, data: Committed, rng: np.random.Generator,
        centres: np.ndarray) -> None:
    data.commit(clustered(rng, 600, centres))
    writer = store(directory, replace(AUTO, index_type="ivf-pq"))
    writer.load(data.total, data.shards)
    reader = store(directory, writable=False)
    reader.load(data.total, data.shards)
    before = reader.active
    first = data.total
    data.commit(clustered(rng, 900, centres))
    writer.after_commit(data.total, data.shards, first)
    writer.persist()  # sealed: 1280 of 1500 vertices in segments
    reader.catch_up(data.total, data.shards)  # from the shards: its tail grows to 988
    assert reader.active is before and reader.persisted == 512
    first = data.total
    data.commit(clustered(rng, 10, centres))
    writer.after_commit(data.total, data.shards, first)
    reader.catch_up(data.total, data.shards)  # a tail of 988 > 2 * 256: reopened instead
    assert reader.active is not before and not before.loaded
    assert reader.persisted == writer.persisted == 1280 and reader.covered == data.total
    writer.close()
