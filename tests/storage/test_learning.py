"""The projection a map learns from its merged edges: the learner's regularisation, its files,
``check``, old maps, automatic retraining, compaction, and kills at every ``learn.*`` point."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sprint_map.config import MapConfig
from sprint_map.map import SprintMap
from sprint_map.storage.check import check_map
from sprint_map.storage.index.model import RowReader
from sprint_map.storage.index.projection import (
    LEARNED,
    PROJECTION_FILE,
    Projection,
    heldout_recall,
    learn_projection,
)
from sprint_map.storage.store import MapStore
from sprint_map.testing.crash import CRASH_ENV, LEARN_POINTS
from tests.helpers import learn_world as world

QUERIES = world.drives(0, views=3)[1]  # later drives of the second condition


def ok(path: Path) -> bool:
    with MapStore.open(path, readonly=True) as store:
        return check_map(store).ok


def search(path: Path) -> np.ndarray:
    with MapStore.open(path, readonly=True) as store:
        return store.search(QUERIES, 3)[1]


# --- the learner ------------------------------------------------------------------------------


def pairs_of(first: np.ndarray, second: np.ndarray) -> tuple[np.ndarray, ...]:
    n = len(first)
    return (np.vstack([first, second]), first, second, np.arange(n), n + np.arange(n))


def test_right_pairs_are_adopted_and_retrieve_better():
    first, second = world.drives(0)
    rows, a, b, ia, ib = pairs_of(first, second)
    report, projection = learn_projection(rows, a, b, ia, ib, dim_out=16, min_pairs=200)
    assert report.adopted and projection is not None
    assert report.heldout_recall_after > report.heldout_recall_before + 0.2
    later_first, later_second = world.drives(0, views=5)
    plain = heldout_recall(later_first, later_second, ia, ia)
    learned = heldout_recall(projection.apply(later_first), projection.apply(later_second),
                             ia, ia)
    assert learned > plain + 0.3


@pytest.mark.parametrize("wrong", [1.0])
def test_wrong_pairs_are_not_adopted(wrong):
    first, second = world.drives(0)
    shuffled = np.random.default_rng(3).permutation(len(second))
    rows, a, b, ia, ib = pairs_of(first, second[shuffled])
    report, projection = learn_projection(rows, a, b, ia, ib + shuffled - np.arange(len(ib)),
                                          dim_out=16, min_pairs=200)
    assert not report.adopted and projection is None
    assert "gain" in report.reason


def test_few_pairs_are_not_adopted():
    first, second = world.drives(0, places=150)
    rows, a, b, ia, ib = pairs_of(first, second)
    report, projection = learn_projection(rows, a, b, ia, ib, dim_out=16, min_pairs=200)
    assert not report.adopted and projection is None
    assert report.pairs == 150 and "fewer" in report.reason


def test_projection_bytes_round_trip_and_batch_independence():
    first, second = world.drives(1)
    rows, a, b, ia, ib = pairs_of(first, second)
    _, projection = learn_projection(rows, a, b, ia, ib, dim_out=16, min_pairs=200)
    assert projection is not None
    again = Projection.from_bytes(projection.to_bytes(), 32, 16)
    whole = again.apply(rows)
    assert np.array_equal(whole[:7], again.apply(rows[:7]))  # check compares row by row
    with pytest.raises(ValueError):
        Projection.from_bytes(projection.to_bytes()[:-4], 32, 16)


# --- the map ----------------------------------------------------------------------------------


def test_learn_rebuilds_the_index_and_no_learn_drops_it(tmp_path):
    path = world.build(tmp_path / "m")
    plain = search(path)
    with SprintMap.open(path) as m:
        before = world.recall(m.store, QUERIES)
        report = m.learn()
        assert set(report) == {"pairs", "dim_in", "dim_out", "adopted",
                               "heldout_recall_before", "heldout_recall_after"}
        assert report["adopted"] and report["pairs"] == world.PLACES
        assert world.recall(m.store, QUERIES) > before + 0.5
        info = m.info()["projection"]
        assert info == {"pairs": world.PLACES, "dim_out": 16, "trained_at_edges": 800}
    assert ok(path)
    assert sorted(p.name for p in (path / "index").iterdir()) == [LEARNED, "p000001"]
    with SprintMap.open(path) as m:
        assert m.unlearn()
        assert m.info()["projection"] is None
    assert np.array_equal(search(path), plain)
    assert not (path / "index" / "p000001").exists()


def test_refused_learning_changes_nothing(tmp_path):
    path = world.build(tmp_path / "m", wrong=1.0)
    plain = search(path)
    with SprintMap.open(path) as m:
        assert not m.learn()["adopted"]
        assert m.info()["projection"] is None
    assert np.array_equal(search(path), plain)


def test_the_writer_retrains_after_learn_every_edges(tmp_path):
    off = world.build(tmp_path / "off")  # learn_every 0: never by itself
    with SprintMap.open(off, readonly=True) as m:
        assert m.info()["projection"] is None
    on = world.build(tmp_path / "on", learn_every=600)  # the drive's commit adds 800 edges
    with SprintMap.open(on, readonly=True) as m:
        assert m.info()["projection"] == {"pairs": world.PLACES, "dim_out": 16,
                                          "trained_at_edges": 800}
        assert world.recall(m.store, QUERIES) > 0.9


def test_check_detects_a_corrupted_projection_and_the_writer_drops_it(tmp_path):
    path = world.build(tmp_path / "m")
    with SprintMap.open(path) as m:
        m.learn()
    target = path / "index" / "p000001" / PROJECTION_FILE
    data = bytearray(target.read_bytes())
    data[100] ^= 0x40
    target.write_bytes(bytes(data))
    with MapStore.open(path, readonly=True) as store:
        report = check_map(store)
        assert not report.ok
        assert any("checksum" in v for v in report.violations), report.violations
        assert store.search(QUERIES, 3)[1].shape == (len(QUERIES), 3)  # plain, from shards
    with MapStore.open(path) as store:
        assert any("dropped the learned projection" in r for r in store.recovery)
    with MapStore.open(path, readonly=True) as store:
        assert check_map(store).ok


def test_check_detects_a_garbled_pointer(tmp_path):
    path = world.build(tmp_path / "m")
    with SprintMap.open(path) as m:
        m.learn()
    (path / "index" / LEARNED).write_bytes(b'{"format": 1, "generation": "x"}')
    with MapStore.open(path, readonly=True) as store:
        report = check_map(store)
    assert not report.ok and any(LEARNED in v for v in report.violations)


class OldConfig:
    """A map's config as sprint-map wrote it before learning existed (no ``learn_*``)."""

    def to_dict(self) -> dict[str, object]:
        record = MapConfig(dim=world.DIM).to_dict()
        for key in ("learn_every", "learn_dim", "learn_min_pairs"):
            del record["store"][key]
        return record


def test_a_map_made_before_learning_opens_and_works_unchanged(tmp_path):
    first, second = world.drives(0)
    path = tmp_path / "old"
    with MapStore.create(path, OldConfig()) as store:
        store.add_sequence(first, name="first")
        store.add_sequence(second, name="second")
        store.flush()
    files = sorted(p.name for p in (path / "index").iterdir())
    with SprintMap.open(path) as m:
        assert m.config.store.learn_every == 0
        assert m.info()["projection"] is None
        m.add_sequence(first[:10], name="more")
    assert ok(path)
    assert all(not name.startswith("p0") and name != LEARNED
               for name in os.listdir(path / "index")), files


def test_compaction_keeps_the_projection(tmp_path):
    path = world.build(tmp_path / "m")
    with SprintMap.open(path) as m:
        m.add_sequence(QUERIES[:5], name="gone")
        m.learn()
        m.remove_sequences(["gone"])
        m.compact()
        assert m.info()["projection"]["pairs"] == world.PLACES
        assert world.recall(m.store, QUERIES) > 0.9
    assert ok(path)


# --- kills at every learn.* point -------------------------------------------------------------

CHILD = """
import sys
from sprint_map.map import SprintMap
with SprintMap.open(sys.argv[1]) as m:
    m.learn() if sys.argv[2] == "learn" else m.unlearn()
print("done", flush=True)
"""


def run_child(path: Path, op: str, point: str | None) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, CRASH_ENV: point} if point else dict(os.environ)
    return subprocess.run([sys.executable, "-c", CHILD, str(path), op], env=env,
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def states(tmp_path_factory):
    """A map before learning, and the search results without and with its projection."""
    base = tmp_path_factory.mktemp("learn") / "base"
    world.build(base)
    plain = search(base)
    done = base.parent / "done"
    shutil.copytree(base, done)
    with SprintMap.open(done) as m:
        m.learn()
    return base, plain, search(done)


@pytest.mark.parametrize(("op", "point"), [("learn", p) for p in LEARN_POINTS]
                         + [("unlearn", p) for p in LEARN_POINTS[1:]])
def test_kill_at_each_learn_point(tmp_path, states, op, point):
    """Killed anywhere in learning (or dropping) a projection: the map has the old projection
    with its index or the new one with its index; a reader open across the kill keeps its
    answers; check passes; the next writer's open removes the rest and a rerun completes."""
    base, plain, learned = states
    path = tmp_path / "m"
    shutil.copytree(base, path)
    if op == "unlearn":
        with SprintMap.open(path) as m:
            m.learn()
    old, new = (plain, learned) if op == "learn" else (learned, plain)
    reader = MapStore.open(path, readonly=True)
    try:
        assert np.array_equal(reader.search(QUERIES, 3)[1], old)  # loaded before the kill
        child = run_child(path, op, point)
        assert child.returncode == -signal.SIGKILL, child.stderr
        assert np.array_equal(reader.search(QUERIES, 3)[1], old)
    finally:
        reader.close()
    published = point == "learn.published"
    assert np.array_equal(search(path), new if published else old)
    with MapStore.open(path, readonly=True) as store:
        report = check_map(store)
    assert report.ok, report.violations
    with MapStore.open(path) as store:  # the writer's open removes what the pointer does not name
        pass
    with MapStore.open(path, readonly=True) as store:
        report = check_map(store)
    assert report.ok and not any("index directory" in n for n in report.notes), report.notes
    names = sorted(p.name for p in (path / "index").iterdir())
    assert len([n for n in names if n.startswith("p0")]) == (
        1 if (op == "learn") == published else 0), names
    assert run_child(path, op, None).stdout.strip() == "done"
    assert np.array_equal(search(path), new)
    with MapStore.open(path, readonly=True) as store:
        assert check_map(store).ok
        info = json.loads((path / "index" / LEARNED).read_text())
        assert bool(info["generation"]) == (op == "learn")


@pytest.mark.parametrize("kind", ["ivf-sq8", "ivf-pq"])
def test_the_segmented_index_searches_the_projection(tmp_path, kind):
    """The approximate index is trained, encoded and re-ranked in the projected space; check
    re-encodes sampled shard rows through the projection and finds the very codes."""
    path = world.build(tmp_path / "m", index_type=kind, index_nlist=8, index_nprobe=8,
                       index_segment_rows=128, index_merge_factor=3, index_train_sample=400)
    with SprintMap.open(path) as m:
        before = world.recall(m.store, QUERIES)
        assert m.learn()["adopted"]
        desc = m.info()["index"]
        assert desc["type"].startswith(f"segmented {kind}") and desc["segments"] >= 1
        assert world.recall(m.store, QUERIES) > before + 0.5
    assert (tmp_path / "m" / "index" / "p000001" / "segments.json").exists()
    with MapStore.open(path, readonly=True) as store:
        report = check_map(store)
        assert report.ok, report.violations
        assert report.checked["index_codes_compared"] > 0
        assert world.recall(store, QUERIES) > before + 0.5


def test_tail_candidates_are_reranked_without_reading_the_shards(tmp_path, monkeypatch):
    """With a projection and no PCA the tail holds projected rows: its candidates are re-ranked
    from there (only sealed candidates are read and projected), at the projected distances."""
    path = world.build(tmp_path / "m", index_type="ivf-sq8", index_nlist=8, index_nprobe=8,
                       index_segment_rows=128, index_merge_factor=3, index_train_sample=400)
    with SprintMap.open(path) as m:
        assert m.learn()["adopted"]
        desc = m.info()["index"]
        sealed = desc["sealed"]
        assert desc["tail"] > 0
        read: list[int] = []
        original = RowReader.rows

        def recording(self, shards, ids, committed):
            read.extend(np.asarray(ids).tolist())
            return original(self, shards, ids, committed)

        monkeypatch.setattr(RowReader, "rows", recording)
        dists, ids = m.store.search(QUERIES, 20)
        assert read and max(read) < sealed <= int(ids.max())
        projection = m.store.index.projection
        mapped = projection.apply(np.vstack(world.drives(0)))  # the map's rows, in id order
        want = ((mapped[ids] - projection.apply(QUERIES)[:, None, :]) ** 2).sum(-1)
        assert np.allclose(dists, want, rtol=1e-4, atol=1e-5)


def test_a_kill_while_learning_writes_an_index_file_leaves_a_note(tmp_path, states):
    """Killed at ``index.partial_written`` during ``index --learn``: the ``.partial`` in the
    projection's folder is the leftover of an interrupted writer, not damage: ``check`` (read
    only) exits 0 with a note, and the next writer's open removes it."""
    from click.testing import CliRunner

    from sprint_map.cli.main import main

    base, _, _ = states
    path = tmp_path / "m"
    shutil.copytree(base, path)
    child = run_child(path, "learn", "index.partial_written")
    assert child.returncode == -signal.SIGKILL, child.stderr
    leftovers = list((path / "index").rglob("*.partial"))
    assert leftovers and all(p.parent.name.startswith("p0") for p in leftovers), leftovers
    result = CliRunner().invoke(main, ["check", str(path), "--json"])
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert report["ok"] and any("leftover temp file" in n for n in report["notes"]), report
    with MapStore.open(path):
        pass
    assert not list((path / "index").rglob("*.partial"))
    assert ok(path)
