"""StoreConfig repeats the storage fields of MapConfig: names, types and defaults must agree."""

from __future__ import annotations

import dataclasses

import pytest

from sprint_map import MapConfig
from sprint_map.config import StoreOptions
from sprint_map.storage.store_config import StoreConfig

STORE_FIELDS = {f.name: f for f in dataclasses.fields(StoreConfig)}
MAP_FIELDS = {f.name: f for f in dataclasses.fields(MapConfig)}


def test_every_storage_field_is_a_map_config_field() -> None:
    assert set(STORE_FIELDS) <= set(MAP_FIELDS)


@pytest.mark.parametrize("name", sorted(STORE_FIELDS))
def test_same_type_and_default_as_map_config(name: str) -> None:
    store, whole = STORE_FIELDS[name], MAP_FIELDS[name]
    assert store.type == whole.type
    assert store.default == whole.default
    assert store.default_factory == whole.default_factory


def test_map_config_hands_storage_its_values() -> None:
    config = MapConfig(dim=8, store=StoreOptions(shard_rows=128, index_nlist=64, initial_map_size=1 << 22))
    assert config.storage == StoreConfig(dim=8, shard_rows=128, index_nlist=64,
                                         initial_map_size=1 << 22)
