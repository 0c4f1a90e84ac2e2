"""MapConfig: nested into its parts (store, HMM, merge rule), one set of defaults, and the flat
records of maps written before the nesting read unchanged."""

from __future__ import annotations

import json

import lmdb
import numpy as np
import pytest

from sprint_map.config import MapConfig, MergeRule, StoreOptions, nest_flat_keys
from sprint_map.errors import ConfigError
from sprint_map.hmm.config import HMMConfig
from sprint_map.map import SprintMap
from sprint_map.storage.lmdb_env import MAX_DBS
from sprint_map.storage.store import LMDB_DIR
from sprint_map.storage.store_config import StoreConfig

#: ``MapConfig(dim=8).to_dict()`` as the code before the nesting wrote it (commit a0a286c).
FLAT_RECORD = {
    "dim": 8, "descriptor": "precomputed", "descriptor_params": {}, "shard_rows": 65536,
    "index_type": "auto", "index_nlist": 1024, "index_nprobe": 16, "index_pq_m": 0,
    "index_pca_dim": 128, "index_rerank": 100, "index_segment_rows": 16384,
    "index_merge_factor": 8, "index_auto_vertices": 200000, "index_train_sample": 65536,
    "index_persist_every": 200000, "index_persist_growth": 1.0, "initial_map_size": 1073741824,
    "merge_threshold": 0.5, "merge_max_novel": 0.2, "merge_window": 3, "merge_min_agree": 0,
    "merge_max_rate": 3.0, "merge_min_run": 20, "merge_dist_quantile": 0.0,
    "merge_min_advance": 0.3, "merge_max_contrast": 0.95, "merge_verify_inliers": 35,
    "merge_both_ways": True,
    "hmm": {"k": 10, "smooth_k": 64, "window": [0.25, 0.5, 0.15, 0.07, 0.03],
            "edge_weight": 1.0, "prune_threshold": 0.0001, "max_active_components": 8,
            "support_threshold": 1e-06, "restart_prob": 0.01, "new_place_prob": 0.01,
            "dist_scale": None, "dist_scale_ema": 0.05, "dist_scale_factor": 0.5,
            "miss_margin": 1.0, "rival_reach": 0, "novelty_margin": 0.25, "novelty_dist": None,
            "novelty_quantile": 0.85, "novelty_window": 100, "place_radius": 2, "place_hops": 4,
            "contrast_reach": 20, "decision_candidates": 4, "min_confidence": 0.2,
            "cache_budget_bytes": 268435456},
}


def test_the_defaults_are_written_once():
    config = MapConfig(dim=8)
    assert config.store == StoreOptions() and config.merge == MergeRule()
    assert config.hmm == HMMConfig()
    # the flat record of the old code says the same defaults, but for its 16 of 1,024 lists,
    # which its maps keep (a new map's lists follow its size)
    assert MapConfig.from_dict(FLAT_RECORD) == config.replace(index_nlist=1024, index_nprobe=16)


def test_the_record_is_nested_and_round_trips():
    config = MapConfig(dim=8, store=StoreOptions(shard_rows=100), merge=MergeRule(min_run=5))
    record = config.to_dict()
    assert record["store"]["shard_rows"] == 100 and record["merge"]["min_run"] == 5
    assert not any(key.startswith(("index_", "merge_")) for key in record)
    assert MapConfig.from_dict(json.loads(json.dumps(record))) == config


@pytest.mark.parametrize(("flat", "field", "value"), [
    ({"index_type": "flat"}, "store.index_type", "flat"),
    ({"merge_min_run": 7}, "merge.min_run", 7),
    ({"merge_both_ways": False}, "merge.both_ways", False),
])
def test_flat_keys_change_their_part(flat, field, value):
    part, name = field.split(".")
    changed = MapConfig(dim=8).replace(**flat)
    assert getattr(getattr(changed, part), name) == value
    assert nest_flat_keys({"dim": 8, **flat})[part] == {name: value}


def test_a_bad_value_is_named_with_its_part():
    with pytest.raises(ConfigError, match=r"MapConfig.merge: min_run must be an integer"):
        MapConfig.from_dict({"dim": 8, "merge": {"min_run": 1.5}})
    with pytest.raises(ConfigError, match="unknown option"):
        MapConfig.from_dict({"dim": 8, "merge": {"gate": 1}})
    with pytest.raises(ValueError, match="index_pq_m"):
        MapConfig(dim=8, store=StoreOptions(index_pq_m=3))


def test_storage_reads_both_forms():
    nested = MapConfig(dim=8, store=StoreOptions(shard_rows=100)).to_dict()
    assert StoreConfig.from_record(nested) == StoreConfig(dim=8, shard_rows=100)
    assert StoreConfig.from_record({**FLAT_RECORD, "shard_rows": 100}) == \
        StoreConfig(dim=8, shard_rows=100, index_nlist=1024, index_nprobe=16)


def test_a_map_written_before_the_nesting_opens_and_works(tmp_path, rng):
    path = tmp_path / "old.map"
    rows = rng.standard_normal((40, 8)).astype(np.float32)
    with SprintMap.create(path, MapConfig(dim=8)) as m:
        m.add_sequence(rows, name="first")
    env = lmdb.open(str(path / LMDB_DIR), max_dbs=MAX_DBS)
    meta = env.open_db(b"meta")
    with env.begin(write=True) as txn:  # the record as the old code stored it
        txn.put(b"config", json.dumps(FLAT_RECORD).encode(), db=meta)
    env.close()
    with SprintMap.open(path) as m:
        assert m.config == MapConfig(dim=8).replace(index_nlist=1024, index_nprobe=16)
        m.ingest(rows + 0.01, name="again")
        assert m.check().ok
    with SprintMap.open(path, readonly=True) as m:
        decisions, _ = m.localize(rows[:30], smooth=True)
        assert len(decisions) == 30
