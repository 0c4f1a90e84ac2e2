"""A summary's rewrite (storage/reduction.py through compact_map): random maps, random
reductions, every invariant after, and the rows, positions, edges and sighting counts as a
reduction means them (hypothesis)."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sprint_map.config import MapConfig, StoreOptions
from sprint_map.errors import InputError
from sprint_map.storage.check import check_map
from sprint_map.storage.records import EdgeRecord, EdgeSpec
from sprint_map.storage.reduction import Reduction
from sprint_map.storage.sightings import scan_sightings
from sprint_map.storage.store import MapStore

DIM = 3
CONFIG = MapConfig(dim=DIM, store=StoreOptions(shard_rows=5))


@st.composite
def maps_and_reductions(draw: st.DrawFn) -> dict:
    """Sequences (lengths, edges to earlier ones, sightings), a removed one maybe, and a
    reduction: per sequence in order a keep mask, a stand-in (kept, older) or none for each
    dropped vertex, stitches and sightings."""
    lengths = draw(st.lists(st.integers(1, 7), min_size=2, max_size=6))
    edges = []  # (seq, image) pairs per sequence, to earlier sequences
    for s, n in enumerate(lengths):
        mine = []
        for _ in range(draw(st.integers(0, 4)) if s else 0):
            other = draw(st.integers(0, s - 1))
            old = (other, draw(st.integers(0, lengths[other] - 1)))
            new = (None, draw(st.integers(0, n - 1)))
            mine.append((new, old) if draw(st.booleans()) else (old, new))
        edges.append(mine)
    removed = draw(st.sampled_from([None, *range(len(lengths))]))
    seen = [(draw(st.integers(0, len(lengths) - 1)), draw(st.integers(0, 6)))
            for _ in range(draw(st.integers(0, 4)))]
    return {"lengths": lengths, "edges": edges, "removed": removed,
            "sightings": [(s, i % lengths[s]) for s, i in seen if s != removed],
            "seed": draw(st.integers(0, 2**16))}


def build(path: Path, spec: dict) -> MapStore:
    rng = np.random.default_rng(spec["seed"])
    store = MapStore.create(path, CONFIG)
    for s, n in enumerate(spec["lengths"]):
        store.add_sequence(rng.standard_normal((n, DIM)).astype(np.float32), name=f"s{s}",
                           positions=rng.uniform(0, 100, (n, 2)),
                           edges=[EdgeSpec(a, b, 0.5, 0) for a, b in spec["edges"][s]])
    if spec["sightings"]:
        store.record_sightings("probe", [(s, i, 1.0) for s, i in spec["sightings"]])
    if spec["removed"] is not None:
        store.remove_sequences([spec["removed"]])
    return store


def random_reduction(store: MapStore, rng: np.random.Generator) -> Reduction:
    total = store.counter("next_vertex_id")
    keep = np.zeros(total, dtype=bool)
    redirect = np.full(total, -1, dtype=np.int64)
    stitches, sightings = [], []
    for seq in sorted(store.sequences(), key=lambda r: r.first_vertex):
        ids = np.arange(seq.first_vertex, seq.last_vertex + 1)
        mask = rng.random(seq.length) < 0.6
        keep[ids] = mask
        older = np.flatnonzero(keep[:seq.first_vertex])
        for v in ids[~mask].tolist():
            if len(older) and rng.random() < 0.7:
                redirect[v] = int(rng.choice(older))
                sightings.append((int(redirect[v]), 0.5, seq.name, 1.0))
        if len(older) and mask.any():
            stitches.append(EdgeRecord(int(rng.choice(older)), int(rng.choice(ids[mask])), 0.7,
                                       seq.seq_id, None, 2e9))
    return Reduction(keep, redirect, stitches, sightings)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(spec=maps_and_reductions())
def test_a_reduction_writes_what_it_means(spec):
    root = Path(tempfile.mkdtemp(prefix="reduction-"))
    try:
        store = build(root / "m", spec)
        with store:
            reduction = random_reduction(store, np.random.default_rng(spec["seed"]))
            before = {s.name: (s, np.array(store.descriptors(s.seq_id)),
                               store.positions(s.seq_id)) for s in store.sequences()}
            old_edges = [(e.src, e.dst) for e in store.edges()]
            with store.env.read() as txn:
                counts = scan_sightings(txn, store.env, {s.seq_id: s.length
                                                         for s in store.sequences()}).total
            keep = reduction.keep
            report = store.summarize(reduction)
            # rows and positions: each sequence's kept frames, in order; none kept: gone
            after = {s.name: s for s in store.sequences()}
            new_id = {}
            for name, (old, rows, pos) in before.items():
                mask = keep[old.first_vertex:old.last_vertex + 1]
                if not mask.any():
                    assert name not in after
                    continue
                rec = after[name]
                assert rec.seq_id == old.seq_id and rec.length == int(mask.sum())
                assert np.array_equal(store.descriptors(rec.seq_id), rows[mask])
                assert np.array_equal(store.positions(rec.seq_id)[:, :2], pos[mask][:, :2])
                for image, v in enumerate((old.first_vertex + np.flatnonzero(mask)).tolist()):
                    new_id[v] = (rec.first_vertex + image, rec.seq_id)
            assert report.vertices_after == int(sum(r.length for r in after.values()))
            # edges: moved onto stand-ins, renumbered, none within a sequence; plus stitches
            expected = set()
            for a, b in old_edges + [(e.src, e.dst) for e in reduction.stitches]:
                a = a if keep[a] else int(reduction.redirect[a])
                b = b if keep[b] else int(reduction.redirect[b])
                if a >= 0 and b >= 0 and new_id[a][1] != new_id[b][1]:
                    expected.add((new_id[a][0], new_id[b][0]))
            assert {(e.src, e.dst) for e in store.edges()} == expected
            # sighting counts: kept ones and moved ones (stand-in or not: a dropped vertex
            # without one loses its record) plus one per reduction sighting
            lost = sum(1 for s, i in spec["sightings"] if s != spec["removed"]
                       and not keep[before[f"s{s}"][0].first_vertex + i]
                       and reduction.redirect[before[f"s{s}"][0].first_vertex + i] < 0)
            with store.env.read() as txn:
                total = scan_sightings(txn, store.env, {s.seq_id: s.length
                                                        for s in store.sequences()}).total
            assert total == counts - lost + len(reduction.sightings)
            report = check_map(store)
            assert report.ok, report.violations
            assert store.removed_vertices() == 0
    finally:
        shutil.rmtree(root, ignore_errors=True)


def test_a_reduction_naming_a_dropped_stand_in_is_refused(tmp_path):
    with MapStore.create(tmp_path / "m", CONFIG) as store:
        store.add_sequence(np.zeros((3, DIM), np.float32), name="a")
        store.add_sequence(np.ones((3, DIM), np.float32), name="b")
        keep = np.array([False, True, True, False, True, True])
        bad = Reduction(keep, np.array([-1, -1, -1, 0, -1, -1]))  # vertex 0 is dropped too
        with pytest.raises(InputError, match="not kept"):
            store.summarize(bad)
        with pytest.raises(InputError, match="cover"):
            store.summarize(Reduction(keep[:4], np.full(4, -1)))
        assert store.stats()["vertices"] == 6 and check_map(store).ok


def test_a_reduction_that_keeps_nothing_leaves_an_empty_map_that_still_grows(tmp_path):
    with MapStore.create(tmp_path / "m", CONFIG) as store:
        store.add_sequence(np.zeros((3, DIM), np.float32), name="a")
        store.add_sequence(np.ones((2, DIM), np.float32), name="b",
                           edges=[EdgeSpec((0, 1), (None, 0), 0.5, 0)])
        report = store.summarize(Reduction(np.zeros(5, dtype=bool), np.full(5, -1)))
        assert report.vertices_after == 0 and store.sequences() == [] and store.edges() == []
        assert check_map(store).ok
        store.add_sequence(np.full((2, DIM), 2, np.float32), name="c")
        assert [s.length for s in store.sequences()] == [2] and check_map(store).ok
