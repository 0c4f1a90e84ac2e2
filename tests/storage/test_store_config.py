"""StoreConfig is storage's view of a map's config: MapConfig.store (StoreOptions) and dim,
with no field written twice."""

from __future__ import annotations

import dataclasses

from sprint_map import MapConfig
from sprint_map.config import StoreOptions
from sprint_map.storage.store_config import StoreConfig


def test_store_config_is_the_options_and_the_dimension() -> None:
    options = {f.name for f in dataclasses.fields(StoreOptions)}
    assert {f.name for f in dataclasses.fields(StoreConfig)} == options | {"dim"}
    # MapConfig holds the options once, as its store part, not as fields of its own
    assert not options & {f.name for f in dataclasses.fields(MapConfig)}


def test_map_config_hands_storage_its_values() -> None:
    config = MapConfig(dim=8, store=StoreOptions(shard_rows=128, index_nlist=64,
                                                 initial_map_size=1 << 22))
    storage = config.storage
    assert storage == StoreConfig(dim=8, shard_rows=128, index_nlist=64, initial_map_size=1 << 22)
    assert storage.options == config.store
