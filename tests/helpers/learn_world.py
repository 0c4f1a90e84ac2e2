"""A synthetic map whose merged edges teach a projection (shared by the learning tests).

Places have a 32-dim identity; the second drive sees each place through a strong nuisance in
a fixed 8-dim subspace (its "condition"), so plain nearest neighbours often miss while a
projection that whitens the within-place differences recovers the place.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sprint_map.config import MapConfig
from sprint_map.storage.records import EdgeSpec
from sprint_map.storage.store import MapStore

DIM = 32
PLACES = 400


def drives(seed: int = 0, places: int = PLACES, views: int = 0
           ) -> tuple[np.ndarray, np.ndarray]:
    """Two drives over the same ``places``: the first plain, the second with a nuisance;
    ``views`` > 0 draws other noise (a later drive of the second condition)."""
    rng = np.random.default_rng(seed)
    identity = rng.standard_normal((places, DIM))
    nuisance = np.linalg.qr(rng.standard_normal((DIM, 8)))[0]
    noise = np.random.default_rng([seed, views]) if views else rng
    first = identity + 0.3 * noise.standard_normal((places, DIM))
    second = (identity + 0.3 * noise.standard_normal((places, DIM))
              + 4.0 * noise.standard_normal((places, 8)) @ nuisance.T)
    return first.astype(np.float32), second.astype(np.float32)


def build(path: Path, *, seed: int = 0, places: int = PLACES, wrong: float = 0.0,
          **config: object) -> Path:
    """A map of the two drives joined by one edge per place (both ways); a fraction
    ``wrong`` of the edges join a random other place instead."""
    first, second = drives(seed, places)
    rng = np.random.default_rng(seed + 1)
    target = np.arange(places)
    bad = rng.random(places) < wrong
    target[bad] = rng.integers(0, places, int(bad.sum()))
    cfg = MapConfig.from_dict({"dim": DIM, "store": {"learn_dim": 16, "learn_min_pairs": 200, **config}})
    with MapStore.create(path, cfg) as store:
        store.add_sequence(first, name="first")
        store.add_sequence(second, name="second", edges=[
            spec for i in range(places) for spec in (
                EdgeSpec((None, i), (0, int(target[i]))), EdgeSpec((0, int(target[i])), (None, i)))])
    return path


def recall(store: MapStore, queries: np.ndarray, places: int = PLACES) -> float:
    """Share of ``queries`` (place i = row i) whose nearest map vertex is a view of place i
    (vertex ``i`` of the first drive or ``places + i`` of the second)."""
    _, ids = store.search(queries, 1)
    return float(np.mean(ids[:, 0] % places == np.arange(len(queries))))
