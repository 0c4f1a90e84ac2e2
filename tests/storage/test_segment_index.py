"""The segmented approximate index: recall, exact re-ranked distances, sealed memory-mapped
segments, tiered merges, the auto switch, crash recovery and untrusted files."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import faiss
import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.config import MapConfig, StoreOptions
from sprint_map.errors import ConfigError
from sprint_map.storage.check import check_map
from sprint_map.storage.index.manifest import MANIFEST, read_manifest
from sprint_map.storage.index.map_index import index_files
from sprint_map.storage.index.segmented import tier_plan
from sprint_map.storage.repair import repair_map
from sprint_map.storage.store import INDEX_DIR, MapStore
from sprint_map.testing.crash import CRASH_ENV, SEGMENT_POINTS

DIM = 32
#: Small segments, a small quantizer: every mechanism fires on a map of a few thousand rows.
SEGMENTED = {"dim": DIM, "index_type": "ivf-pq", "index_nlist": 16, "index_nprobe": 8,
             "index_segment_rows": 256, "index_merge_factor": 3, "index_train_sample": 2000,
             "index_rerank": 50}


def clustered(rng: np.random.Generator, n: int, centres: np.ndarray) -> np.ndarray:
    """Points around ``centres`` (real descriptors cluster; random ones would not)."""
    return (centres[rng.integers(len(centres), size=n)]
            + 0.15 * rng.standard_normal((n, centres.shape[1]))).astype(np.float32)


def exact(rows: np.ndarray, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    d = ((queries[:, None, :] - rows[None, :, :]) ** 2).sum(-1)
    ids = np.argsort(d, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(d, ids, axis=1), ids


@pytest.fixture
def centres(rng):
    return rng.standard_normal((300, DIM)).astype(np.float32)


def build(path: Path, rng, centres, lengths, **config) -> np.ndarray:
    rows = []
    with MapStore.create(path, MapConfig.from_dict({**SEGMENTED, **config})) as store:
        for n in lengths:
            rows.append(clustered(rng, n, centres))
            store.add_sequence(rows[-1])
    return np.concatenate(rows)


def search_all(path: Path, queries: np.ndarray, k: int):
    with MapStore.open(path, readonly=True) as store:
        return store.search(queries, k)


# --- configuration ---------------------------------------------------------------------------


def test_config_defaults_validation_and_old_maps():
    assert MapConfig(dim=128).store.index_type == "auto"
    assert MapConfig(dim=1764).index_dim == 128 and MapConfig(dim=64).index_dim == 64
    assert MapConfig(dim=128).pq_m == 16 and MapConfig(dim=12).pq_m == 1
    old = MapConfig.from_dict({"dim": 8, "index_type": "flat", "shard_rows": 64,
                               "index_nlist": 1024})
    assert old.store.index_type == "flat" and old.store.index_nlist == 1024
    assert MapConfig(dim=8).store.index_nlist == 0  # lists follow the map's size
    assert MapConfig.from_dict({"dim": 8, "index_nlist": 8}).store.index_nprobe == 24  # all 8
    for bad in ({"index_type": "hnsw"}, {"index_nprobe": 0}, {"index_nlist": -1}, {"index_nlist": 2.5}, {"index_train_sample": 0},
                {"index_pq_m": 7}, {"index_merge_factor": 1}, {"index_train_sample": 10},
                {"index_retrain_growth": 1.0}, {"index_retrain_growth": -2}):
        with pytest.raises(ConfigError):
            MapConfig.from_dict({"dim": 128, **bad})


def test_tier_plan_is_what_sealing_and_merging_leave():
    assert tier_plan(10 * 256 + 17, 256, 3) == [(0, 2304), (2304, 2560)]
    assert tier_plan(100, 256, 3) == []
    plan = tier_plan(26 * 100, 100, 3)
    assert [b - a for a, b in plan] == [900, 900, 300, 300, 100, 100]
    capped = tier_plan(26 * 100, 100, 3, max_rows=300)  # no merge past 300 rows
    assert [b - a for a, b in capped] == [300] * 8 + [100, 100]
    assert tier_plan(26 * 100, 100, 3, max_rows=299) == tier_plan(26 * 100, 100, 3, 100)
    assert [(a, b) for a, b in capped] == [(300 * i, 300 * (i + 1)) for i in range(8)] + [
        (2400, 2500), (2500, 2600)]


# --- retrieval --------------------------------------------------------------------------------


def test_recall_and_exact_distances(tmp_path, rng, centres):
    rows = build(tmp_path / "m", rng, centres, [1500, 1500, 700])
    queries = clustered(rng, 60, centres)
    dist, ids = search_all(tmp_path / "m", queries, 10)
    _, want = exact(rows, queries, 10)
    recall = np.mean([len(set(a) & set(b)) for a, b in zip(ids.tolist(), want.tolist(),
                                                           strict=True)]) / 10
    assert recall >= 0.9
    # Re-ranked from the shards: the distances of the returned ids are exact, ascending.
    true = ((queries[:, None, :] - rows[ids]) ** 2).sum(-1)
    np.testing.assert_allclose(dist, true, rtol=1e-5)
    assert np.all(np.diff(dist, axis=1) >= 0)
    # Every stored row finds itself (in a segment or in the tail).
    _, self_ids = search_all(tmp_path / "m", rows[::37], 1)
    np.testing.assert_array_equal(self_ids[:, 0], np.arange(len(rows))[::37])


# 3,700 rows: segments [0, 2304), [2304, 3072), [3072, 3328), [3328, 3584) and a tail of 116
@pytest.mark.parametrize("ranges", [
    [(0, 2304), (2304, 3328), (3328, None)],  # at segment ends: no selector
    [(0, 1000), (1000, 3500), (3500, None)],  # inside segments and the tail: a selector
    [(3600, None), (0, 3600)],
])
def test_a_search_within_ranges_keeps_to_them(tmp_path, rng, centres, ranges):
    rows = build(tmp_path / "m", rng, centres, [1500, 1500, 700])
    queries = np.concatenate([clustered(rng, 40, centres), rows[::150]])
    _, want = exact(rows, queries, 10)
    with MapStore.open(tmp_path / "m", readonly=True) as store:
        assert store.index_segments() == [(0, 2304), (2304, 3072), (3072, 3328), (3328, 3584)]
        whole = store.search(queries, 10)
        parts = [store.search_within(queries, 10, a, b) for a, b in ranges]
    for (a, b), (dist, ids) in zip(ranges, parts, strict=True):
        b = len(rows) if b is None else b
        found = ids[ids >= 0]
        assert ((found >= a) & (found < b)).all() and len(found) == ids.size
        true = ((queries[:, None, :] - rows[ids]) ** 2).sum(-1)  # re-ranked: exact
        np.testing.assert_allclose(dist, true, rtol=1e-5)
    # the k best of the ranges' k best: every range re-ranks its own candidates, so at least
    # the recall of the whole map's search, and every row finds itself
    merged = np.concatenate([p[1] for p in parts], axis=1)
    order = np.argsort(np.concatenate([p[0] for p in parts], axis=1), axis=1, kind="stable")
    merged = np.take_along_axis(merged, order, axis=1)[:, :10]

    def recall(ids):
        return np.mean([len(set(a) & set(b)) for a, b in zip(ids.tolist(), want.tolist(),
                                                            strict=True)])

    assert recall(merged) >= recall(whole[1]) and recall(merged) >= 9.0
    np.testing.assert_array_equal(merged[40:, 0], np.arange(0, len(rows), 150))


def test_a_search_within_hides_removed_and_needs_the_approximate_index(tmp_path, rng, centres):
    rows = build(tmp_path / "m", rng, centres, [1500, 1500, 700])
    with MapStore.open(tmp_path / "m") as store:
        store.remove_sequences([1])  # vertices [1500, 3000)
    with MapStore.open(tmp_path / "m", readonly=True) as store:
        _, ids = store.search_within(rows[1400:1600], 5, 1000, 2000)
    assert ((ids >= 1000) & (ids < 1500)).all()
    flat = tmp_path / "flat"
    with MapStore.create(flat, MapConfig(dim=DIM, store=StoreOptions(index_type="flat"))) as s:
        s.add_sequence(rows[:100])
        assert s.index_segments() == []
        with pytest.raises(ValueError, match="approximate"):
            s.search_within(rows[:1], 1, 0, 50)


def test_over_fetching_and_padding(tmp_path, rng, centres):
    rows = build(tmp_path / "m", rng, centres, [600])
    dist, ids = search_all(tmp_path / "m", rows[:3], 200)  # k above index_rerank
    assert ids.shape == (3, 200) and (ids >= 0).all() and len(set(ids[0])) == 200
    far, few = search_all(tmp_path / "m", rows[:1], 1000)  # more than the map holds
    found = int((few[0] >= 0).sum())  # what the probed lists hold: at most the map
    assert 200 <= found <= 600 and len(set(few[0, :found])) == found
    assert (few[0, found:] == -1).all() and (far[0, found:] == np.finfo(np.float32).max).all()


@pytest.mark.parametrize("max_rows", [0, 768])
def test_segments_sealed_merged_and_memory_mapped(tmp_path, rng, centres, max_rows):
    rows = build(tmp_path / "m", rng, centres, [300] * 10 + [100],  # 3100 rows
                 index_segment_max_rows=max_rows)
    manifest = read_manifest(tmp_path / "m" / INDEX_DIR)
    # 12 blocks of 256 sealed one at a time, tiers of 3 merged: 2304 + 768 + 0 ... + tail,
    # or with merges stopped at 768 rows: 4 x 768
    assert [(s.start, s.stop) for s in manifest.segments] == tier_plan(3100, 256, 3, max_rows)
    assert len(manifest.segments) == (2 if not max_rows else 4)
    assert manifest.sealed == 3072 and manifest.kind == "ivf-pq"
    files = sorted(p.name for p in (tmp_path / "m" / INDEX_DIR).iterdir())
    assert files == sorted([MANIFEST, f"model.{manifest.generation:06d}.faiss"]
                           + [s.file for s in manifest.segments])
    with MapStore.open(tmp_path / "m", readonly=True) as store:
        store.search(rows[:1], 5)
        seg = store.index.active
        assert seg is not None and seg.tail_len == 28
        assert len(seg.segments) == len(manifest.segments)
        for index in seg.segments:
            lists = faiss.downcast_InvertedLists(index.invlists)
            assert isinstance(lists, faiss.OnDiskInvertedLists)  # IO_FLAG_MMAP: not copied
        report = check_map(store)
    assert report.ok, report.violations
    assert report.checked["index_segments"] == len(manifest.segments)
    assert report.checked["index_codes_compared"] > 0


@pytest.mark.parametrize(("max_rows", "merged"), [
    (0, [(0, 1280)]),
    # 1400 rows: five blocks of 256 sealed, none merged (a tier of 768 would pass 600); then
    # runs of at most 600 rows
    (600, [(0, 512), (512, 1024), (1024, 1280)]),
])
def test_merge_segments_keeps_results(tmp_path, rng, centres, max_rows, merged):
    rows = build(tmp_path / "m", rng, centres, [1400], index_segment_max_rows=max_rows)
    queries = clustered(rng, 20, centres)
    before = search_all(tmp_path / "m", queries, 10)
    with MapStore.open(tmp_path / "m") as store:
        store.search(queries[:1], 1)
        assert store.index.merge_segments()
        assert [(s.start, s.stop) for s in read_manifest(tmp_path / "m" / INDEX_DIR).segments
                ] == merged
        assert not store.index.merge_segments()  # nothing left to merge
    after = search_all(tmp_path / "m", queries, 10)
    np.testing.assert_array_equal(before[1], after[1])
    assert len(rows) == 1400


def test_auto_switches_from_flat_when_the_map_grows(tmp_path, rng, centres):
    # auto at dim 32 switches once vertices * 32 >= 1000 * 128, i.e. at 4000 vertices.
    path = tmp_path / "m"
    config = {"index_type": "auto", "index_auto_vertices": 1000, "index_persist_every": 500}
    rows = build(path, rng, centres, [1500, 1500], **config)
    assert index_files(path / INDEX_DIR) and not (path / INDEX_DIR / MANIFEST).exists()
    with MapStore.open(path) as store:
        rows = np.concatenate([rows, clustered(rng, 1200, centres)])
        store.add_sequence(rows[3000:])
        assert not store.index.active.exact
        assert any("index trained" in e for e in store.index.events)
    assert not index_files(path / INDEX_DIR)  # the flat file went once the segments were named
    assert read_manifest(path / INDEX_DIR).trained_on == 4200
    _, ids = search_all(path, rows[::50], 1)
    np.testing.assert_array_equal(ids[:, 0], np.arange(0, len(rows), 50))


@pytest.mark.parametrize("growth", [0, 2.0])
def test_the_writer_retrains_as_the_map_grows(tmp_path, rng, centres, growth):
    # trained at 300 vertices; with growth 2 trained again once the map holds 600
    path = tmp_path / "m"
    rows = build(path, rng, centres, [300], index_retrain_growth=growth)
    first = read_manifest(path / INDEX_DIR)
    assert first.trained_on == 300
    with MapStore.open(path) as store:
        for n in (250, 50, 400):
            rows = np.concatenate([rows, clustered(rng, n, centres)])
            store.add_sequence(rows[-n:])
            manifest = store.index.active.manifest
            if growth and len(rows) >= 600:
                assert manifest.trained_on == (600 if len(rows) < 1200 else len(rows))
                assert manifest.generation > first.generation
            else:
                assert manifest == first or manifest.generation == first.generation
    assert read_manifest(path / INDEX_DIR).trained_on == (600 if growth else 300)
    with MapStore.open(path, readonly=True) as store:
        report = check_map(store)
    assert report.ok, report.violations
    dists, ids = search_all(path, rows[::25], 1)
    np.testing.assert_array_equal(ids[:, 0], np.arange(0, len(rows), 25))
    assert np.allclose(dists[:, 0], 0.0)


def test_lists_follow_the_map_as_it_is_retrained(tmp_path, rng, centres):
    # index_nlist 0: sqrt(4 * trained_on) lists, each retraining with more (the sample grows
    # to feed them: 39 per list, at most the map); a map made with fixed lists keeps them
    path = tmp_path / "m"
    rows = build(path, rng, centres, [1000], index_nlist=0, index_train_sample=256,
                 index_segment_rows=2048)
    assert read_manifest(path / INDEX_DIR).nlist == 1000 // 39  # the whole map: 25 lists' worth
    with MapStore.open(path) as store:
        for n in (7000, 24000):  # trained again at 8,000 (4x 1,000), then at 32,000
            rows = np.concatenate([rows, clustered(rng, n, centres)])
            store.add_sequence(rows[-n:])
            manifest = store.index.active.manifest
            assert (manifest.trained_on, manifest.nlist) == {
                8000: (8000, 179), 32000: (32000, 358)}[len(rows)]  # sqrt(4 * trained_on)
    with MapStore.open(path, readonly=True) as store:
        report = check_map(store)
    assert report.ok, report.violations
    # the same rows under 16 fixed lists (the 1,024 of old maps, scaled down): lists of
    # 2,000 rows, where the grown map's hold ~90; it finds fewer of its own rows
    fixed = tmp_path / "fixed"
    config = MapConfig.from_dict({**SEGMENTED, "index_train_sample": 256,
                                  "index_segment_rows": 2048})
    with MapStore.create(fixed, config) as store:
        store.add_sequence(rows)
    assert read_manifest(fixed / INDEX_DIR).nlist == 16
    every = np.arange(0, len(rows), 40)
    found = {p: np.mean(search_all(p, rows[every], 1)[1][:, 0] == every) for p in (path, fixed)}
    assert found[path] > 0.85 and found[path] > found[fixed], found


def test_the_service_retrains_beside_the_searches(tmp_path, rng, centres):
    # Deferred (a service): the commit does not retrain; retrain_index_beside does, while
    # another thread keeps searching under the shared side of a lock; only the switch takes
    # the exclusive side.
    import threading
    from contextlib import contextmanager

    path = tmp_path / "m"
    rows = build(path, rng, centres, [300], index_retrain_growth=2.0)
    lock = threading.Lock()
    switches = []

    @contextmanager
    def exclusive():
        with lock:
            switches.append(len(found))
            yield

    found: list[bool] = []
    stop = threading.Event()
    with MapStore.open(path) as store:
        store.index.defer_retrain = True
        more = clustered(rng, 400, centres)
        store.add_sequence(more)
        rows = np.concatenate([rows, more])
        assert store.index.active.manifest.trained_on == 300  # not inside the commit

        def search() -> None:
            i = 0
            while not stop.is_set():
                with lock:
                    _, ids = store.search(rows[i % len(rows)][None], 1)
                found.append(int(ids[0, 0]) == i % len(rows))
                i += 7

        searcher = threading.Thread(target=search)
        searcher.start()
        try:
            assert store.retrain_index_beside(exclusive)
        finally:
            stop.set()
            searcher.join()
        assert store.index.active.manifest.trained_on == 700
        assert not store.retrain_index_beside(exclusive)  # not due again
    assert found and all(found)
    assert len(switches) == 2
    with MapStore.open(path, readonly=True) as store:
        report = check_map(store)
        assert report.ok, report.violations
        assert not [n for n in report.notes if "not in the manifest" in n]
    _, ids = search_all(path, rows[::20], 1)
    np.testing.assert_array_equal(ids[:, 0], np.arange(0, len(rows), 20))


# --- untrusted files --------------------------------------------------------------------------


def test_torn_and_ahead_segments_are_dropped(tmp_path, rng, centres):
    path = tmp_path / "m"
    rows = build(path, rng, centres, [1000])
    shutil.copytree(path, tmp_path / "older")  # the map as it was: 1000 vertices
    with MapStore.open(path) as store:
        more = clustered(rng, 2000, centres)
        store.add_sequence(more)
    # The older map's LMDB with the newer index: segments past its 1000 vertices are ahead.
    shutil.rmtree(tmp_path / "older" / INDEX_DIR)
    shutil.copytree(path / INDEX_DIR, tmp_path / "older" / INDEX_DIR)
    with MapStore.open(tmp_path / "older", readonly=True) as store:
        assert any("ahead of the map" in v for v in check_map(store).violations)
    with MapStore.open(tmp_path / "older") as store:
        assert any("ahead of the map (1000 vertices): dropped" in r for r in store.recovery)
    manifest = read_manifest(tmp_path / "older" / INDEX_DIR)
    assert manifest.sealed <= 1000
    _, ids = search_all(tmp_path / "older", rows[::25], 1)
    np.testing.assert_array_equal(ids[:, 0], np.arange(0, 1000, 25))

    # A torn segment (cut short): it and every segment after it are dropped, the tail takes
    # over their range, and the next seal puts them back.
    first = read_manifest(path / INDEX_DIR).segments[0]
    with open(path / INDEX_DIR / first.file, "r+b") as f:
        f.truncate(first.bytes // 2)
    with MapStore.open(path, readonly=True) as store:
        assert any("is torn" in v for v in check_map(store).violations)
        _, ids = store.search(more[:5], 1)  # a reader leaves it out, searches the tail
        np.testing.assert_array_equal(ids[:, 0], np.arange(1000, 1005))
    with MapStore.open(path) as store:
        assert any("is torn" in r for r in store.recovery)
        assert read_manifest(path / INDEX_DIR).segments == ()
        store.search(more[:1], 1)
        store.flush()  # seals the tail again
    with MapStore.open(path, readonly=True) as store:
        assert check_map(store).ok
        assert read_manifest(path / INDEX_DIR).sealed == 2816


def test_garbled_manifest_is_retrained(tmp_path, rng, centres):
    path = tmp_path / "m"
    rows = build(path, rng, centres, [800])
    (path / INDEX_DIR / MANIFEST).write_text("{not json")
    with MapStore.open(path) as store:
        assert any("manifest" in r for r in store.recovery)
        assert not (path / INDEX_DIR / MANIFEST).exists()
        _, ids = store.search(rows[:4], 1)  # the writer trains a new index on first use
    np.testing.assert_array_equal(ids[:, 0], np.arange(4))
    assert read_manifest(path / INDEX_DIR) is not None


# --- crashes (real processes killed at each named point) -------------------------------------

CHILD = """
import sys, numpy as np
from sprint_map.storage.store import MapStore
path, mode, DIM = sys.argv[1], sys.argv[2], int(sys.argv[3])
with MapStore.open(path) as store:
    if mode in ("add", "grow", "beside"):  # grow: past 3x the vertices trained on, retrained
        rng = np.random.default_rng(5)
        store.index.defer_retrain = mode == "beside"
        if mode == "beside":  # killed in the retraining only, not in the commit's seal
            import contextlib, os
            from sprint_map.testing.crash import CRASH_ENV
            point = os.environ.pop(CRASH_ENV, None)
        store.add_sequence(rng.standard_normal((700, DIM)).astype(np.float32) * 3)
        if mode == "beside":  # (a service's writer thread, between commits)
            store.index.active.wait()
            if point:
                os.environ[CRASH_ENV] = point
            store.retrain_index_beside(contextlib.nullcontext)
    else:
        store.rebuild_index(train=True)
"""


def run_child(path: Path, mode: str, point: str | None) -> int:
    env = {**os.environ, CRASH_ENV: point} if point else dict(os.environ)
    return subprocess.run([sys.executable, "-c", CHILD, str(path), mode, str(DIM)], env=env,
                          capture_output=True, timeout=120).returncode


@pytest.mark.parametrize("mode", ["add", "train", "grow", "beside"])
@pytest.mark.parametrize("point", SEGMENT_POINTS)
def test_kill_at_each_segment_point(tmp_path, rng, centres, point, mode):
    """Killed while training, sealing or publishing: the map is intact, a writer's open
    removes the leftovers, the index (old or new) finds every vertex, check passes."""
    path = tmp_path / "m"
    # 200 vertices: flat (below MIN_TRAIN); "train" mode starts from a trained index; "grow"
    # from one trained on 256, retrained by the commit that brings the map to 956.
    lengths = {"add": [200], "train": [200, 700], "grow": [256], "beside": [256]}[mode]
    rows = build(path, rng, centres, lengths, index_retrain_growth=3.0)
    before = read_manifest(path / INDEX_DIR)
    assert mode == "add" or before.trained_on == sum(lengths)
    assert run_child(path, mode, point) == -9
    with MapStore.open(path, readonly=True) as store:
        total = store.stats()["vertices"]
        report = check_map(store)
        assert report.ok, report.violations  # leftovers are notes, never violations
        all_rows = store.shards.rows(0, total, total).copy()
    assert total == sum(lengths) + (0 if mode == "train" else 700)
    assert mode == "add" or np.array_equal(all_rows[: len(rows)], rows)
    if mode != "add":  # readers still have the old generation whole
        assert read_manifest(path / INDEX_DIR).generation == before.generation + (
            point == "index.manifest_published")
    with MapStore.open(path) as store:
        named = {n for n, _ in read_manifest(path / INDEX_DIR).files()} if (
            path / INDEX_DIR / MANIFEST).exists() else set()
        leftovers = {p.name for p in (path / INDEX_DIR).iterdir()} - named - {MANIFEST}
        assert not leftovers - {p.name for _, p in index_files(path / INDEX_DIR)}
        _, ids = store.search(all_rows, 1)
        np.testing.assert_array_equal(ids[:, 0], np.arange(total))
    with MapStore.open(path, readonly=True) as store:
        report = check_map(store)
        assert report.ok and not [n for n in report.notes if "not in the manifest" in n]
    assert run_child(path, mode, None) == 0  # and the writer carries on


# --- the index command -----------------------------------------------------------------------


def run_cli(*args: object):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def test_cli_index_train_rebuild_and_show(tmp_path, rng, centres):
    path = tmp_path / "m"
    rows = build(path, rng, centres, [900])
    with MapStore.open(path, readonly=True) as reader:  # a reader with the old index loaded
        _, before = reader.search(rows[:5], 3)
        # Another process retrains (LMDB allows one environment per process).
        result = subprocess.run([sys.executable, "-c", "from sprint_map.cli.main import main; main()",
                                 "index", str(path), "--train", "--json"],
                                capture_output=True, text=True, timeout=120)
        assert result.returncode == 0, result.stderr
        data = json.loads(result.stdout)
        assert data["index"]["generation"] == 2 and "trained" in data["done"][0]
        # The old generation's files are gone, but the reader's mapped copies still answer.
        _, still = reader.search(rows[:5], 3)
        np.testing.assert_array_equal(before, still)
    assert {p.name for p in (path / INDEX_DIR).iterdir()} >= {"model.000002.faiss", MANIFEST}
    assert not (path / INDEX_DIR / "model.000001.faiss").exists()
    result = run_cli("index", path, "--rebuild")
    assert result.exit_code == 0 and "segmented ivf-pq" in result.output
    shown = run_cli("index", path)
    assert shown.exit_code == 0 and "generation" not in shown.output
    assert "index: segmented ivf-pq (IVF16)" in shown.output
    assert run_cli("check", path).exit_code == 0
    missing = run_cli("index", tmp_path / "nothing", "--train")
    assert missing.exit_code == 3 and missing.output.startswith("Error: ")


def test_cli_index_on_a_flat_map(tmp_path, rng, centres):
    path = tmp_path / "flat"
    build(path, rng, centres, [300], index_type="flat")
    result = run_cli("index", path, "--train")
    assert result.exit_code == 0 and "flat" in result.output
    assert index_files(path / INDEX_DIR) and not (path / INDEX_DIR / MANIFEST).exists()


def test_check_repair_restores_a_torn_segment_index(tmp_path, rng, centres):
    path = tmp_path / "m"
    rows = build(path, rng, centres, [1200])
    last = read_manifest(path / INDEX_DIR).segments[-1]
    with open(path / INDEX_DIR / last.file, "ab") as f:
        f.write(b"garbage")  # padded: its size is no longer the recorded one
    report = repair_map(path)
    assert any(f"{last.file} is torn" in r for r in report.found + report.repaired)
    assert report.ok, report.after.violations
    assert report.after.checked["index_segments"] >= 1
    _, ids = search_all(path, rows[::40], 1)
    np.testing.assert_array_equal(ids[:, 0], np.arange(0, 1200, 40))


def test_compact_retrains_and_merges_a_segmented_index(tmp_path, rng, centres):
    """The removal interface: removed vertices never come back, compact rebuilds the index
    (retrained on the renumbered vertices) and merges it into one segment."""
    path = tmp_path / "m"
    rows = build(path, rng, centres, [600, 600, 600])
    with MapStore.open(path) as store:
        store.search(rows[:1], 1)
        store.remove_sequences([1])
        _, ids = store.search(rows[600:1200:50], 10)
        assert not ((ids >= 600) & (ids < 1200)).any()
        store.compact()
        manifest = read_manifest(store.data_path / INDEX_DIR)
        assert len(manifest.segments) == 1 and manifest.trained_on == 1200
        kept = np.concatenate([rows[:600], rows[1200:]])
        _, ids = store.search(kept[::30], 1)
        np.testing.assert_array_equal(ids[:, 0], np.arange(0, 1200, 30))
        assert check_map(store).ok
