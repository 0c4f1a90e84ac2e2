"""The ``SprintMap`` facade over the store: lifecycle, reads, writes, info and check."""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.config import SCHEMA_VERSION, MapConfig, MergeRule, StoreOptions
from sprint_map.errors import MapLockedError, NotAMapError, ReadOnlyMapError
from sprint_map.frontend.centring import CentringStats, DriveCentring
from sprint_map.map import SprintMap
from sprint_map.storage.index.map_index import index_files
from sprint_map.storage.records import EdgeSpec
from sprint_map.storage.store import INDEX_DIR

DIM = 6


@pytest.fixture
def config() -> MapConfig:
    return MapConfig(dim=DIM, store=StoreOptions(shard_rows=10, index_persist_every=1000), merge=MergeRule(threshold=0.3))


@pytest.fixture
def drives(rng) -> list[np.ndarray]:
    return [rng.standard_normal((n, DIM)).astype(np.float32) for n in (4, 13, 9)]


@pytest.fixture
def map_path(tmp_path, config, drives):
    """A closed map of three drives; drive 1 linked to drive 0, drive 2 on its own."""
    path = tmp_path / "city.map"
    with SprintMap.create(path, config) as m:
        m.add_sequence(drives[0], name="mon", positions=np.zeros((4, 2)))
        m.add_sequence(drives[1], name="tue", edges=[EdgeSpec((None, 2), (0, 1), weight=0.9,
                                                              frame=2)])
        m.add_sequence(drives[2], name="wed", source="cam1")
    return path


def test_reopened_map_reads_back_what_was_added(map_path, config, drives):
    with SprintMap.open(map_path, readonly=True) as m:
        assert m.readonly
        assert m.path == map_path
        assert m.config == config
        assert [s.name for s in m.sequences()] == ["mon", "tue", "wed"]
        assert m.sequence(2).source == "cam1"
        for seq_id, drive in enumerate(drives):
            # stored centred on the drive's running mean, the earlier drives' mean as its prior
            prior = CentringStats.pool(m.drive_stats(j) for j in range(seq_id))  # type: ignore[misc]
            want = DriveCentring(config.centring, DIM, prior).apply(drive)
            assert m.descriptors(seq_id).tobytes() == want.tobytes()
            stats = m.drive_stats(seq_id)
            assert stats is not None and stats.frames == len(drive)
            np.testing.assert_allclose(stats.mean, drive.mean(0), atol=1e-6)
        np.testing.assert_array_equal(m.positions(0)[:, :2], np.zeros((4, 2)))
        assert m.positions(1) is None
        assert m.stats() == {"sequences": 3, "vertices": 26, "edges": 1, "components": 2}
        assert m.component_of(0) == m.component_of(1) != m.component_of(2)
        assert sorted(c.sequences for c in m.components()) == [[0, 1], [2]]
        _, ids = m.search(np.concatenate(drives), k=1)
        np.testing.assert_array_equal(ids[:, 0], np.arange(26))
        report = m.check()
        assert report.ok, report.violations


def test_info_is_cheap_and_complete(map_path, config):
    with SprintMap.open(map_path, readonly=True) as m:
        info = m.info()
        assert m.store.index.index is None  # info did not load the index
    assert info["schema_version"] == SCHEMA_VERSION
    assert (info["sequences"], info["vertices"], info["edges"], info["components"]) == (3, 26, 1, 2)
    assert (info["dim"], info["descriptor"]) == (DIM, "precomputed")
    # Nothing searched yet, so nothing persisted; a search would still cover all 26.
    assert (info["index"]["ntotal"], info["index"]["persisted"]) == (26, 0)
    assert info["disk_bytes"] >= 26 * DIM * 4
    assert MapConfig.from_dict(info["config"]) == config


def test_flush_persists_the_index_and_info_reports_it(map_path, drives, rng):
    with SprintMap.open(map_path) as m:
        m.search(drives[0][:1], k=1)
        m.add_sequence(rng.standard_normal((5, DIM)))
        m.flush()
        assert [u for u, _ in index_files(map_path / INDEX_DIR)] == [31]
        assert m.info()["index"]["persisted"] == 31
    with SprintMap.open(map_path, readonly=True) as m:
        assert m.info()["index"]["persisted"] == 31  # from the file name, without loading


def test_readonly_facade_refuses_writes(map_path, drives):
    with SprintMap.open(map_path, readonly=True) as m:
        with pytest.raises(ReadOnlyMapError):
            m.add_sequence(drives[0])
        with pytest.raises(ReadOnlyMapError):
            m.flush()
        assert m.stats()["sequences"] == 3


def test_facade_open_errors(tmp_path, map_path):
    with pytest.raises(NotAMapError):
        SprintMap.open(tmp_path / "nowhere")
    with SprintMap.open(map_path), pytest.raises(MapLockedError):
        SprintMap.open(map_path)
    SprintMap.open(map_path).close()  # the refused open left no lock behind


def test_close_is_idempotent(map_path):
    m = SprintMap.open(map_path)
    m.close()
    m.close()
    SprintMap.open(map_path).close()
