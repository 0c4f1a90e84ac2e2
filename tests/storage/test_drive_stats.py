"""Per-drive statistics (``drive_stats``): committed with the drive, kept by the map's writers,
checked and repaired; a map stored before centring reads as uncentred."""

from __future__ import annotations

import json

import lmdb
import numpy as np
import pytest

from sprint_map.config import MapConfig, StoreOptions
from sprint_map.frontend.centring import Centring, DriveCentring
from sprint_map.map import SprintMap
from sprint_map.storage.drive_stats import DRIVE_STATS_DB
from sprint_map.storage.keys import u32

DIM = 8


@pytest.fixture
def drives() -> list[np.ndarray]:
    rng = np.random.default_rng(5)
    return [(rng.standard_normal((n, DIM)) + 3 * rng.standard_normal(DIM)).astype(np.float32)
            for n in (30, 20, 25)]


@pytest.fixture
def config() -> MapConfig:
    return MapConfig(dim=DIM, store=StoreOptions(shard_rows=16), centring=Centring("drive"))


def build(path, config, drives) -> None:
    with SprintMap.create(path, config) as m:
        for i, rows in enumerate(drives):
            m.ingest(rows, name=f"d{i}", merge=False)


def lmdb_path(path):
    return str(path / "map.lmdb")


def test_each_drive_stores_its_frames_and_mean(tmp_path, config, drives):
    build(tmp_path / "m", config, drives)
    with SprintMap.open(tmp_path / "m", readonly=True) as m:
        for i, rows in enumerate(drives):
            stats = m.drive_stats(f"d{i}")
            assert stats is not None and stats.frames == len(rows)
            np.testing.assert_allclose(stats.mean, rows.mean(0), rtol=1e-5, atol=1e-5)
        assert m.check().ok
        assert m.check().checked["drive_stats"] == 3


def test_remove_forgets_them_compact_and_summarize_keep_them(tmp_path, config, drives):
    build(tmp_path / "m", config, drives)
    with SprintMap.open(tmp_path / "m") as m:
        before = m.drive_stats("d2")
        m.remove_sequences(["d1"])
        assert m.check().ok and m.check().checked["drive_stats"] == 2
        m.compact()
        after = m.drive_stats("d2")
        assert after is not None and before is not None
        assert after.frames == before.frames and after.mean.tobytes() == before.mean.tobytes()
        m.summarize()
        kept = m.drive_stats("d2")
        assert kept is not None and kept.mean.tobytes() == before.mean.tobytes()
        assert m.check().ok


def test_the_prior_is_the_maps_mean_condition(tmp_path, config, drives):
    build(tmp_path / "m", config, drives[:2])
    with SprintMap.open(tmp_path / "m") as m:
        prior = m.service.condition_prior()
        assert prior is not None and prior.frames == 50
        want = (drives[0].astype(np.float64).sum(0) + drives[1].sum(0)) / 50
        np.testing.assert_allclose(prior.mean, want, rtol=1e-5, atol=1e-5)
        m.ingest(drives[2], name="d2", merge=False)  # stored centred with that prior
        expect = DriveCentring(config.centring, DIM, prior).apply(drives[2])
        assert m.descriptors(2).tobytes() == expect.tobytes()
        assert m.service.condition_prior().frames == 75  # pooled again after the commit


def test_check_finds_a_broken_record_and_repair_drops_it(tmp_path, config, drives):
    build(tmp_path / "m", config, drives)
    env = lmdb.open(lmdb_path(tmp_path / "m"), max_dbs=24)
    with env.begin(write=True) as txn:
        db = env.open_db(DRIVE_STATS_DB.encode(), txn=txn)
        txn.put(u32(1), b"\x00" * 5, db=db)  # wrong length
        txn.put(u32(99), txn.get(u32(0), db=db), db=db)  # a sequence the map does not hold
    env.close()
    with SprintMap.open(tmp_path / "m", readonly=True) as m:
        report = m.check()
    assert not report.ok and "drive_stats" in report.areas
    assert sum("drive statistics" in v for v in report.violations) == 2
    repaired = SprintMap.repair(tmp_path / "m")
    assert repaired.ok, repaired
    with SprintMap.open(tmp_path / "m", readonly=True) as m:
        assert m.check().ok
        assert m.drive_stats("d1") is None and m.drive_stats("d0") is not None


def test_a_map_stored_before_centring_reads_uncentred(tmp_path, drives):
    config = MapConfig(dim=DIM, centring=Centring("none"))
    build(tmp_path / "old", config, drives[:1])
    env = lmdb.open(lmdb_path(tmp_path / "old"), max_dbs=24)
    with env.begin(write=True) as txn:  # the config record as an older sprint-map wrote it
        meta = env.open_db(b"meta", txn=txn)
        record = json.loads(txn.get(b"config", db=meta))
        del record["centring"]
        txn.put(b"config", json.dumps(record).encode(), db=meta)
    env.close()
    with SprintMap.open(tmp_path / "old") as m:
        assert m.config.centring == Centring("none")
        m.ingest(drives[1], name="new", merge=False)
        assert m.descriptors(1).tobytes() == drives[1].tobytes()  # its space: as described
    assert MapConfig(dim=DIM).centring.mode == "none"  # centring is opt-in
