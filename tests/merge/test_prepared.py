"""``stale_reason`` (sprint_map/merge/prepared.py), without Ray: a drive localised against a
snapshot is committed as prepared only if serial ingest would decide it the same way now."""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.config import MapConfig
from sprint_map.map import SprintMap
from sprint_map.merge.prepared import prepare_drive, stale_reason
from sprint_map.storage.records import EdgeSpec
from sprint_map.storage.store_config import StoreOptions
from tests.helpers.worlds import drive, random_places

DIM = 16


@pytest.fixture
def areas(rng):
    """Two areas of 80 places, far apart in descriptor space."""
    return random_places(rng, 80, DIM), random_places(rng, 80, DIM) * -1


@pytest.fixture
def smap(tmp_path, rng, areas):
    """A map (exact flat index) with one drive over each area."""
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM, store=StoreOptions(index_type="flat"))) as m:
        for n, places in enumerate(areas):
            m.add_sequence(drive(places, rng, 0.1), name=f"base{n}")
        yield m


def prepared(smap, rows, **kwargs):
    return prepare_drive(smap, np.array_split(rows, 3), **kwargs)


def test_nothing_committed_since_the_snapshot_is_not_stale(smap, rng, areas):
    rows = drive(areas[0], rng, 0.1)
    assert stale_reason(smap, prepared(smap, rows), rows) is None


def test_a_drive_appended_without_merging_is_never_stale(smap, rng, areas):
    rows = drive(areas[0], rng, 0.1)
    kept = prepared(smap, rows, merge=False)
    smap.add_sequence(drive(areas[0], rng, 0.1), name="meanwhile")
    assert not kept.localised and stale_reason(smap, kept, rows) is None


def test_a_drive_prepared_on_an_empty_map_is_stale_once_the_map_has_rows(tmp_path, rng, areas):
    rows = drive(areas[0], rng, 0.1)
    with SprintMap.create(tmp_path / "e", MapConfig(dim=DIM, store=StoreOptions(index_type="flat"))) as m:
        kept = prepared(m, rows)
        assert not kept.localised and stale_reason(m, kept, rows) is None
        m.add_sequence(drive(areas[1], rng, 0.1), name="first")
        assert stale_reason(m, kept, rows) == "the map was empty at the snapshot"


def test_a_vertex_among_a_frames_neighbours_makes_it_stale(smap, rng, areas):
    rows = drive(areas[0], rng, 0.1)
    kept = prepared(smap, rows)
    smap.add_sequence(drive(areas[0], rng, 0.05), name="same-streets")
    assert stale_reason(smap, kept, rows) == (
        "a vertex committed since the snapshot is among a frame's k nearest")


def test_a_far_drive_with_no_edge_into_the_touched_components_is_not_stale(smap, rng, areas):
    rows = drive(areas[0], rng, 0.1)
    kept = prepared(smap, rows)
    far = random_places(rng, 50, DIM)
    far[:, 0] += 50.0  # nowhere near any frame of the drive
    smap.add_sequence(far, name="elsewhere")
    assert stale_reason(smap, kept, rows) is None


def test_a_touched_component_that_grew_makes_it_stale(smap, rng, areas):
    rows = drive(areas[0], rng, 0.1)
    kept = prepared(smap, rows)
    far = random_places(rng, 50, DIM)
    far[:, 0] += 50.0
    base0 = smap.sequences()[0].seq_id
    smap.add_sequence(far, name="joined", edges=[EdgeSpec((None, 0), (base0, 0), 0.9)])
    assert stale_reason(smap, kept, rows) == f"component {base0} changed since the snapshot"


def test_a_removal_since_the_snapshot_makes_it_stale(smap, rng, areas):
    rows = drive(areas[0], rng, 0.1)
    kept = prepared(smap, rows)
    smap.add_sequence(random_places(rng, 10, DIM) + 50.0, name="gone")
    smap.remove_sequences(["gone"])
    assert stale_reason(smap, kept, rows) == "sequences were removed since the snapshot"
