"""``compact``: the space of removed sequences reclaimed, vertex ids renumbered consistently
(edges, positions, descriptors bit for bit), readers open across a compaction, and the CLI of
``remove`` and ``compact``. Kills at every compaction step: ``tests/storage/test_crash.py``."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.config import StoreOptions
from sprint_map.errors import UnknownSequenceError
from sprint_map.storage.check import check_map
from sprint_map.storage.generation import CURRENT_NAME
from sprint_map.storage.records import EdgeSpec
from sprint_map.storage.store import SHARDS_DIR, MapStore
from tests.helpers import crash_worker

logical_state = crash_worker.logical_state


def strict_check(path: Path) -> None:
    with MapStore.open(path, readonly=True) as store:
        report = check_map(store)
    assert report.ok and not report.notes, (report.violations, report.notes)


def shard_bytes(data: Path) -> int:
    return sum(p.stat().st_size for p in (data / SHARDS_DIR).iterdir())


@pytest.mark.parametrize("shard_rows", [7, 64, 4096])
def test_compaction_reclaims_the_space_and_renumbers_consistently(make_map, rng, shard_rows):
    lengths = [int(x) for x in rng.integers(20, 120, 10)]
    built = make_map(lengths, dim=32, shard_rows=shard_rows, edges=3)
    removed = sorted(int(s) for s in rng.choice(10, 5, replace=False))
    with MapStore.open(built.path) as store:
        store.search(built.all_descriptors()[:1], 1)  # an index to reclaim too
        store.remove_sequences(removed)
        before = logical_state(store)
        report = store.compact()
        assert logical_state(store) == before  # the writer goes on with the new generation
    live = [s for s in built.sequences if s.seq_id not in removed]
    live_rows = sum(s.length for s in live)
    with MapStore.open(built.path, readonly=True) as store:
        assert logical_state(store) == before
        assert store.data_path.name == report.generation == "gen-000001"
        # dense again: sequences in order, first vertices the running sum, nothing removed
        firsts = [r.first_vertex for r in store.sequences()]
        assert firsts == np.cumsum([0] + [s.length for s in live])[:-1].tolist()
        assert store.stats()["vertices"] == live_rows and store.removed_vertices() == 0
        assert shard_bytes(store.data_path) == live_rows * 32 * 4
        rows = np.concatenate([s.descriptors for s in live])
        _, ids = store.search(rows, 1)  # every row its own nearest neighbour, new ids
        assert ids[:, 0].tolist() == list(range(live_rows))
    assert report.vertices_before == built.vertices and report.vertices_after == live_rows
    assert report.bytes_after < report.bytes_before
    assert report.parts_after["shards"] < report.parts_before["shards"]
    assert report.parts_after["map.lmdb"] < report.parts_before["map.lmdb"]
    assert report.old_generation_removed
    assert sorted(p.name for p in built.path.iterdir()) == [CURRENT_NAME, "LOCK", "gen-000001"]
    strict_check(built.path)


def test_the_map_goes_on_after_compactions(make_map, rng):
    built = make_map((30, 40, 50), dim=8, shard_rows=16, edges=2)
    with MapStore.open(built.path) as store:
        store.remove_sequences([0])
        store.compact()
        added = store.add_sequence(rng.standard_normal((10, 8)).astype(np.float32),
                                   edges=[EdgeSpec((None, 0), (2, 5))]).sequence
        assert (added.seq_id, added.first_vertex) == (3, 90)
        store.remove_sequences([1])
        assert store.compact().generation == "gen-000002"
        state = logical_state(store)
    with MapStore.open(built.path) as store:
        assert logical_state(store) == state
        assert [(r.seq_id, r.first_vertex) for r in store.sequences()] == [(2, 0), (3, 50)]
        assert store.component_of(3) == store.component_of(2)
    strict_check(built.path)


def test_compacting_an_empty_or_untouched_map(make_map, rng):
    built = make_map((5, 6), edges=1)
    with MapStore.open(built.path) as store:
        state = logical_state(store)
        store.compact()  # nothing removed: the same map, LMDB copied compactly
        assert logical_state(store) == state
        store.remove_sequences([0, 1])
        report = store.compact()
        assert (report.sequences, report.vertices_after) == (0, 0)
        assert store.stats() == {"sequences": 0, "vertices": 0, "edges": 0, "components": 0}
        store.add_sequence(rng.standard_normal((3, 8)).astype(np.float32), name="again")
    strict_check(built.path)


READER = """
import sys, numpy as np
from sprint_map.storage.store import MapStore
store = MapStore.open(sys.argv[1], readonly=True)
print(store.data_path.name, flush=True)
sys.stdin.readline()  # the parent compacts meanwhile
rows = np.concatenate([store.descriptors(r.seq_id) for r in store.sequences()])
_, ids = store.search(rows, 1)
print(len(rows), int((ids[:, 0] == np.arange(len(rows))).all()), rows.sum().item(), flush=True)
from sprint_map.storage.check import check_map
report = check_map(store)
print(int(report.ok), int(any("compacted since into gen-000001" in n for n in report.notes)),
      flush=True)
store.close()
"""


def test_a_reader_open_across_a_compaction_keeps_its_generation(make_map):
    built = make_map((30, 40, 50), dim=8, shard_rows=16, edges=2)
    with MapStore.open(built.path) as store:
        store.remove_sequences([1])
        total = sum(r.length for r in store.sequences())
        want = float(np.concatenate([store.descriptors(r.seq_id)
                                     for r in store.sequences()]).sum())
    reader = subprocess.Popen([sys.executable, "-c", READER, str(built.path)],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert reader.stdout is not None and reader.stdin is not None
        assert reader.stdout.readline().strip() == built.path.name  # generation 0: the top
        with MapStore.open(built.path) as store:
            report = store.compact()
        assert not report.old_generation_removed  # pinned by the reader
        with MapStore.open(built.path, readonly=True) as store:
            assert any("not the live generation" in n for n in check_map(store).notes)
        reader.stdin.write("\n")
        reader.stdin.flush()
        n, self_hits, checksum = reader.stdout.readline().split()
        # the old view, whole: its own vertex ids (with the removed range), its own rows
        assert (int(n), int(self_hits)) == (total, 0)
        assert float(checksum) == pytest.approx(want)
        assert reader.stdout.readline().split() == ["1", "1"]  # its check: ok, and says so
    finally:
        reader.kill()
        reader.wait()
    with MapStore.open(built.path) as store:  # the reader is gone: the old generation goes
        assert store.recovery == ["removed generation 0 (top level), no longer the live "
                                  "generation"]
    strict_check(built.path)


def test_removal_by_id_or_name_through_the_facade(make_map):
    from sprint_map.map import SprintMap

    built = make_map((5, 6, 7), edges=2)
    with SprintMap.open(built.path) as m:
        result = m.remove_sequences([0, built.sequences[2].name])
        assert [r.seq_id for r in result.removed] == [0, 2]
        with pytest.raises(UnknownSequenceError):
            m.remove_sequences(["no such drive"])
        assert m.info()["removed_vertices"] == 12
        m.compact()
        assert m.info()["removed_vertices"] == 0 and m.info()["generation"] == "gen-000001"


def run(*args: object):
    return CliRunner().invoke(main, [str(a) for a in args], catch_exceptions=False)


def test_cli_remove_and_compact(make_map, tmp_path):
    built = make_map((20, 30, 40), dim=8, edges=3)
    for command in ("remove", "compact"):
        assert "Example" in run(command, "--help").output
    result = run("remove", built.path, "0", built.sequences[2].name, "--json")
    assert result.exit_code == 0, result.output
    data = json.loads(result.output)
    assert [r["seq_id"] for r in data["removed"]] == [0, 2]
    assert data["vertices_removed"] == 60
    result = run("remove", built.path, "1", "7")
    assert result.exit_code == UnknownSequenceError.exit_code
    assert result.output.strip() == "Error: no sequence 7 in the map"
    result = run("compact", built.path, "--json")
    assert result.exit_code == 0, result.output
    report = json.loads(result.output)
    assert (report["vertices_before"], report["vertices_after"]) == (90, 30)
    assert report["bytes_after"] < report["bytes_before"]
    text = run("compact", built.path).output
    assert text.startswith("compacted into gen-000002: 30 -> 30 vertices")
    assert run("check", built.path).exit_code == 0
    sequences = json.loads(run("sequences", built.path, "--json").output)
    assert [(s["seq_id"], s["frames"]) for s in sequences] == [(1, 30)]


def test_an_io_error_at_any_file_call_of_a_compaction_leaves_a_whole_map(make_map, tmp_path):
    """EIO on each file call of ``compact`` in turn (``storage/faults.py``): before the switch
    the compaction fails with a one-line ``StorageIOError`` and the old map stays; after it
    (removing the old generation) it succeeds with a warning. Either way the map means the
    same, and after the next writer's open ``check`` is strict."""
    import errno
    import shutil

    from sprint_map.errors import StorageIOError
    from sprint_map.testing.faults import CallRecorder, FaultInjector, installed

    built = make_map((12, 20, 9), dim=8, shard_rows=16, edges=2)
    with MapStore.open(built.path) as store:
        store.remove_sequences([1])
        store.search(built.all_descriptors()[:1], 1)
        state = logical_state(store)
    template = tmp_path / "template"
    shutil.copytree(built.path, template)
    recorder = CallRecorder()
    with MapStore.open(built.path) as store, installed(recorder):
        store.compact()
    assert {op for op, _ in recorder.calls} >= {"write", "fsync", "fsync_dir", "replace",
                                                "unlink"}
    outcomes = set()
    for n in range(1, len(recorder.calls) + 1):
        path = tmp_path / f"case-{n}"
        shutil.copytree(template, path)
        store = MapStore.open(path)
        try:
            with installed(FaultInjector(n, errno.EIO, seed=n)):
                store.compact()
            outcomes.add("compacted, " + ("warned" if store.warnings else "clean"))
        except StorageIOError as exc:
            assert "\n" not in str(exc) and "(injected)" in str(exc), (n, exc)
            outcomes.add("failed")
        finally:
            store.close()
        with MapStore.open(path, readonly=True) as reader:
            assert logical_state(reader) == state, n
            assert check_map(reader).ok, n
        MapStore.open(path).close()  # removes the generation left behind, if any
        strict_check(path)
        shutil.rmtree(path)
    assert outcomes == {"failed", "compacted, warned"}


def test_remove_and_compact_with_the_approximate_index(tmp_path, rng):
    """Six drives of one road in a segmented IVF-SQ8 index: after removing three, searches hit
    only the others; compaction retrains the index over the renumbered vertices and merges its
    segments into one."""
    from sprint_map.config import MapConfig

    place = rng.standard_normal((1000, 32)).astype(np.float32)
    config = MapConfig(dim=32, store=StoreOptions(index_type="ivf-sq8", index_nlist=16, index_segment_rows=500))
    with MapStore.create(tmp_path / "m", config) as store:
        for _ in range(6):
            store.add_sequence(place + 0.3 * rng.standard_normal((1000, 32)).astype(np.float32))
        store.remove_sequences([0, 2, 4])
        _, ids = store.search(place[:100], 10)
        assert (ids >= 0).all()
        assert {s for s, _ in store.locate(ids.ravel())} <= {1, 3, 5}
        state = logical_state(store)
        store.flush()  # seals every full block now (the worker may still be sealing one)
        assert store.index.describe()["segments"] > 1
        store.compact()
        described = store.index.describe()
        assert described["type"].startswith("segmented ivf-sq8")
        assert (described["segments"], described["sealed"]) == (1, 3000)  # merged into one
        _, ids = store.search(place[:100], 10)
        assert (ids >= 0).all() and ids.max() < 3000
        assert logical_state(store) == state
    with MapStore.open(tmp_path / "m", readonly=True) as store:
        assert check_map(store).ok
