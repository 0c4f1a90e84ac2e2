"""Crash consistency with real processes and real SIGKILLs.

(a) A process SIGKILLs itself at each named crash point of every write path (adding a sequence,
persisting the index, a writer's recovery at open, ``check --repair``); (b) writers are killed
at random instants, over and over, and restarted. After every kill the map must pass ``check``,
hold every acknowledged sequence bit for bit, hold each other sequence either wholly or not at
all, and have the components of its edges. Writers add the deterministic stream of
``tests/helpers/crash_worker.py``, so the test regenerates what each sequence must contain.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import faiss
import numpy as np
import pytest

from sprint_map.config import StoreOptions
from sprint_map.storage.check import check_map
from sprint_map.storage.generation import CURRENT_NAME
from sprint_map.storage.index.map_index import index_files
from sprint_map.storage.keys import u32, u64
from sprint_map.storage.records import EdgeSpec
from sprint_map.storage.store import INDEX_DIR, SHARDS_DIR, MapStore
from sprint_map.testing.crash import (
    ADD_POINTS,
    COMPACT_POINTS,
    CRASH_POINTS,
    GROUP_POINTS,
    INDEX_POINTS,
    JOIN_POINTS,
    LEARN_POINTS,
    RECOVER_POINTS,
    REMOVE_POINTS,
    REPAIR_POINTS,
    SEGMENT_POINTS,
    SIGHTING_POINTS,
    SUMMARIZE_POINTS,
    UNMERGE_POINTS,
)
from tests.helpers import crash_worker

worker = crash_worker
verify = worker.verify
create_map = worker.create_map


@pytest.fixture(scope="module")
def zygote(tmp_path_factory):
    z = worker.Zygote(tmp_path_factory.mktemp("zygote") / "zygote.log")
    yield z
    z.close()


def run_child(zygote: Any, ack: Path, **request: Any) -> list[str]:
    """Run one zygote child to its end; return the lines it acknowledged."""
    status = zygote.run(ack=str(ack), **request)
    if request.get("crash_at"):
        assert status["signal"] == signal.SIGKILL, (status, zygote.log.read_text())
    else:
        assert status == {"signal": None, "code": 0}, zygote.log.read_text()
    return worker.read_lines(ack)


def shard(path: Path, n: int) -> Path:
    return path / SHARDS_DIR / f"shard-{n:06d}.f32"


SEED, LENGTH = 7, 40


@pytest.fixture
def three(tmp_path):
    """A map with three acknowledged sequences of 40 rows (shard_rows=64: shard 1 is open).

    Persisting the index after every add makes the index crash points fire inside an add.
    """
    path = tmp_path / "m"
    create_map(path, dim=8, shard_rows=64, index_persist_every=1, index_persist_growth=0)
    with MapStore.open(path) as store:
        for i in range(3):
            worker.add_planned(store, SEED, i, LENGTH)
    return path


def continue_stream(path: Path, upto: int) -> list[str]:
    """A writer's open (recovery), then the stream continues to ``upto`` sequences."""
    with MapStore.open(path) as store:
        recovery = store.recovery
        for i in range(store.stats()["sequences"], upto):
            worker.add_planned(store, SEED, i, LENGTH)
    report = verify(path, SEED, set(range(upto)), LENGTH)
    assert report.ok, report.violations
    worker.assert_search_finds_everything(path)
    return list(recovery)


# --- (a) named crash points: adding a sequence, persisting the index --------------------------

PRESENT_AFTER = {"add.committed", *INDEX_POINTS}


@pytest.mark.parametrize("point", ADD_POINTS + INDEX_POINTS)
def test_kill_at_each_write_point(three, zygote, point):
    path = three
    lines = run_child(zygote, path.parent / "ack", map=str(path), seed=SEED, count=3,
                      length=LENGTH, crash_at=point)
    assert lines == ["ready"]  # killed inside its first add: sequence 3 (with thumbnails)

    report = verify(path, SEED, {0, 1, 2}, LENGTH)
    with MapStore.open(path, readonly=True) as store:
        in_flight_committed = store.stats()["sequences"] == 4
    assert in_flight_committed == (point in PRESENT_AFTER)
    assert report.ok, report.violations  # a leftover temp file is a note: the map is whole
    if point == "index.partial_written":
        assert any(n.startswith("leftover temp file index/flat.000000000160.faiss.partial")
                   for n in report.notes), report.notes
    # Killed after the rows were written but before the commit: 8 rows (of 32 bytes) past the
    # committed end of shard 1, and an uncommitted shard 2.
    rows_written_uncommitted = point in {"add.shards_written", "add.thumbnails_written",
                                         "add.before_commit"}
    if rows_written_uncommitted:
        assert any("shard-000001.f32 has 256 uncommitted bytes" in n for n in report.notes)
        assert any("shard-000002.f32 holds no committed row" in n for n in report.notes)
    if point in {"add.committed", "index.partial_written"}:
        # The index file still covers the first three sequences; the first search after the
        # crash must catch up from the shards (continue_stream checks it).
        assert "index lags the map by 40 vertices (caught up on load)" in report.notes

    recovery = continue_stream(path, 6)
    if rows_written_uncommitted:
        assert recovery == ["truncated shard-000001.f32 to 56 committed rows",
                            "removed uncommitted shard shard-000002.f32"]
    elif point == "index.partial_written":
        assert recovery == ["removed leftover temp file flat.000000000160.faiss.partial"]
    else:
        assert recovery == []


# --- a writer's recovery at open -------------------------------------------------------------


@pytest.mark.parametrize("point", RECOVER_POINTS)
def test_kill_during_recovery_at_open(three, zygote, point):
    """Killed while its open cleans up after an earlier kill: the next open finishes the job."""
    path = three
    run_child(zygote, path.parent / "ack1", map=str(path), seed=SEED, count=1, length=LENGTH,
              crash_at="add.shards_written")  # uncommitted rows in shards 1 and 2
    (path / INDEX_DIR / "flat.000000000999.faiss.partial").write_bytes(b"torn")
    (_, persisted), = index_files(path / INDEX_DIR)
    shutil.copy(persisted, path / INDEX_DIR / "flat.000000000200.faiss")  # ahead of the map

    lines = run_child(zygote, path.parent / "ack2", map=str(path), seed=SEED, length=LENGTH,
                      crash_at=point)
    assert lines == []  # killed inside the open, before "ready"

    report = verify(path, SEED, {0, 1, 2}, LENGTH)
    assert report.violations == ["index file flat.000000000200.faiss is ahead of the map "
                                 "(120 vertices)"]
    truncated = point == "recover.shards_truncated"
    assert any("uncommitted bytes" in n for n in report.notes) != truncated
    assert continue_stream(path, 5) == (
        [] if truncated else ["truncated shard-000001.f32 to 56 committed rows",
                              "removed uncommitted shard shard-000002.f32"]
    ) + ["removed index flat.000000000200.faiss: ahead of the map (120 vertices)"]


# --- check --repair ---------------------------------------------------------------------------


def damage_everything_derivable(path: Path) -> None:
    """Break one record of every derivable area, plus shard tails, temp files and the index."""
    with MapStore.open(path) as store:
        db = store.env.db
        joined = next(c for c in store.components() if len(c.sequences) > 1)
        other = next(s for s in joined.sequences if s != joined.component)

        def body(txn: Any) -> None:
            store.uf.add(txn, other, 1)  # split off a joined sequence: components
            cursor = txn.cursor(db=db("edges_rev"))
            assert cursor.first()
            cursor.delete()  # edge_index
            txn.put(b"n_sequences", u64(99), db=db("meta"))  # lookup
            txn.put(u32(0), u64(5), db=db("shards"))  # shard_lengths

        store.env.write(body)
        total = store.stats()["vertices"]
        rows = np.array(store.shards.rows(0, total, total))
    with shard(path, 0).open("ab") as f:  # garbage past a sealed shard
        f.write(b"\x7f" * 10)
    with shard(path, 2).open("ab") as f:  # a torn append to the open shard
        f.write(b"\x01" * 50)
    (path / SHARDS_DIR / "shard-000002.f32.partial").write_bytes(b"x")
    (path / "meta.partial").write_bytes(b"x")
    (_, file), = index_files(path / INDEX_DIR)
    rows[0] += 1  # an index whose vectors are not the shards' (same stamp, same size)
    index = faiss.IndexIDMap2(faiss.IndexFlatL2(rows.shape[1]))
    index.add_with_ids(rows, np.arange(len(rows)))
    faiss.write_index(index, str(file))


def repair_in_child(zygote: Any, path: Path, ack: Path, crash_at: str | None = None
                    ) -> dict[str, Any] | None:
    lines = run_child(zygote, ack, map=str(path), mode="repair", crash_at=crash_at)
    done = [json.loads(line.split(" ", 1)[1]) for line in lines if line.startswith("repaired ")]
    return done[0] if done else None


@pytest.mark.parametrize("point", RECOVER_POINTS + REPAIR_POINTS + INDEX_POINTS)
def test_kill_at_each_repair_point(tmp_path, zygote, point):
    """Killed anywhere in ``check --repair``: the map opens, and repairing again converges."""
    path = tmp_path / "m"
    create_map(path, dim=8, shard_rows=64, index_persist_every=1, index_persist_growth=0)
    with MapStore.open(path) as store:  # 160 rows: shards 0 and 1 sealed, 2 open
        for i in range(4):
            worker.add_planned(store, SEED, i, LENGTH)
    damage_everything_derivable(path)
    with MapStore.open(path, readonly=True) as store:
        assert check_map(store).areas == {"lookup", "shard_lengths", "edge_index", "components",
                                          "index"}

    assert repair_in_child(zygote, path, tmp_path / "ack1", crash_at=point) is None  # killed
    with MapStore.open(path, readonly=True) as store:  # still a map, the data intact
        assert [s.name for s in store.sequences()] == [f"w-{i}" for i in range(4)]
    done = repair_in_child(zygote, path, tmp_path / "ack2")
    assert done is not None and done["ok"], done
    again = repair_in_child(zygote, path, tmp_path / "ack3")
    assert again == {**done, "found": [], "repaired": []}  # converged: nothing left to do
    report = verify(path, SEED, set(range(4)), LENGTH)
    assert report.ok and not report.notes, (report.violations, report.notes)
    worker.assert_search_finds_everything(path)


# --- every crash point is real and exercised ------------------------------------------------


def test_every_crash_point_is_in_the_code_and_tested():
    names = set()
    for source in Path(worker.__file__).parents[2].joinpath("sprint_map").rglob("*.py"):
        names |= set(re.findall(r'crash_point\("([^"]+)"\)', source.read_text()))
    assert names == set(CRASH_POINTS)
    tested = set(ADD_POINTS + INDEX_POINTS) | set(RECOVER_POINTS) | set(REPAIR_POINTS)
    tested |= set(REMOVE_POINTS) | set(COMPACT_POINTS)  # test_kill_at_each_{remove,compact}_point
    tested |= set(UNMERGE_POINTS)  # test_kill_at_each_unmerge_point
    tested |= set(SEGMENT_POINTS)  # tests/storage/test_segment_index.py (kill at each)
    tested |= set(GROUP_POINTS)  # tests/merge/test_drives.py (a real multi-drive ingest killed)
    tested |= set(LEARN_POINTS)  # tests/storage/test_learning.py (learn and unlearn killed)
    tested |= set(SIGHTING_POINTS)  # tests/merge/test_admission.py (an admitted drive killed)
    tested |= set(SUMMARIZE_POINTS)  # tests/merge/test_merge_summary.py (summarize killed at each)
    tested |= set(JOIN_POINTS)  # test_kill_at_each_join_point
    assert tested == set(CRASH_POINTS)


# --- join -------------------------------------------------------------------------------------

JOIN_CLI = [sys.executable, "-c", "from sprint_map.cli.main import main; main()"]


def join_maps_for_crash(root: Path) -> tuple[Path, Path]:
    """TARGET with two drives of a road, SOURCE with two more (merged) and one elsewhere."""
    from sprint_map.config import MapConfig
    from sprint_map.map import SprintMap
    from tests.helpers.road_map import DIM, Road

    rng = np.random.default_rng(3)
    road, other = Road.make(rng), Road.make(rng, origin=(0.0, 900.0))
    target, source = root / "target", root / "source"
    for path, names in ((target, ["t0", "t1"]), (source, ["s0", "s1", "far"])):
        with SprintMap.create(path, MapConfig(dim=DIM, store=StoreOptions(shard_rows=64))) as m:
            for i, name in enumerate(names):
                desc, xy = other.drive(rng, 50) if name == "far" else road.drive(rng, 80, 3 * i)
                m.ingest(desc, name=name, positions=xy)
    return target, source


def join_state(path: Path) -> dict[str, Any]:
    """The sequences (with their rows), edges with provenance and components; check passes."""
    from sprint_map.map import SprintMap

    with SprintMap.open(path, readonly=True) as m:
        assert m.check().ok, m.check().to_dict()
        return {"sequences": [(s.seq_id, s.name, s.length, m.descriptors(s.seq_id).tobytes())
                              for s in m.sequences()],
                "edges": [(e.to_dict(), e.frame) for e in m.edges()],
                "components": [(c.component, c.sequences) for c in m.components()]}


@pytest.mark.parametrize("point", JOIN_POINTS + GROUP_POINTS[1:])
def test_kill_at_each_join_point(tmp_path, point):
    """A real ``sprint-map join`` SIGKILLed at each point of its path: TARGET is as before the
    join (killed before the commit point) or as after it, and passes check; the same command
    run again then completes the join (or finds it done) with the clean join's result."""
    target, source = join_maps_for_crash(tmp_path)
    clean = tmp_path / "clean"
    shutil.copytree(target, clean)
    subprocess.run([*JOIN_CLI, "join", str(clean), str(source)], check=True, timeout=300,
                   capture_output=True)
    before, after = join_state(target), join_state(clean)
    env = {**os.environ, "SPRINT_MAP_CRASH_AT": point}
    proc = subprocess.run([*JOIN_CLI, "join", str(target), str(source)], env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    killed = join_state(target)
    committed = point in {"group.committed", "join.committed"}
    assert killed == (after if committed else before)
    again = subprocess.run([*JOIN_CLI, "join", str(target), str(source), "--json"],
                           capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert join_state(target) == after
    assert json.loads(again.stdout)["imported"] == (0 if committed else 3)


# --- remove and compact -----------------------------------------------------------------------

REMOVED = [1, 4]


@pytest.fixture
def six(tmp_path):
    """Six acknowledged sequences of 40 rows (shards of 64 rows), the index persisted."""
    path = tmp_path / "m"
    create_map(path, dim=8, shard_rows=64)
    with MapStore.open(path) as store:
        for i in range(6):
            worker.add_planned(store, SEED, i, LENGTH)
    return path


def state_of(path: Path) -> dict[str, Any]:
    with MapStore.open(path, readonly=True) as store:
        return worker.logical_state(store)


def without(state: dict[str, Any], removed: list[int]) -> dict[str, Any]:
    """``state`` with ``removed`` and every edge touching them gone (components: the
    networkx components of what remains, checked by ``logical_state`` itself)."""
    seqs = {k: v for k, v in state["sequences"].items() if k not in removed}
    edges = {e for e in state["edges"] if e[0][0] not in removed and e[1][0] not in removed}
    return {"sequences": seqs, "edges": edges}


strictly_ok = worker.strictly_ok


@pytest.mark.parametrize("point", REMOVE_POINTS)
def test_kill_at_each_remove_point(six, zygote, point):
    """Killed while removing: all of the removal or none of it, and check passes."""
    path = six
    before = state_of(path)
    lines = run_child(zygote, path.parent / "ack", map=str(path), mode="remove", seqs=REMOVED,
                      crash_at=point)
    assert lines == ["ready"]
    after = state_of(path)
    if point == "remove.committed":
        assert {k: after[k] for k in ("sequences", "edges")} == without(before, REMOVED)
        assert after["stats"]["sequences"] == 4
    else:
        assert after == before
    strictly_ok(path)
    with MapStore.open(path) as store:  # the map goes on: a compaction completes
        store.compact()
    assert {k: state_of(path)[k] for k in ("sequences", "edges")} == (
        without(before, REMOVED) if point == "remove.committed" else without(before, []))
    strictly_ok(path)


@pytest.mark.parametrize("point", COMPACT_POINTS)
def test_kill_at_each_compact_point(six, zygote, point):
    """Killed anywhere in ``compact``: the old map or the new one, each intact (every live
    sequence bit for bit, the removed ones absent, the components of the edges, check passing
    but for notes on the unselected generation); the next writer's open removes the other
    generation and a compaction run again completes."""
    path = six
    with MapStore.open(path) as store:
        store.remove_sequences(REMOVED)
        total = store.stats()["vertices"]
    expected = state_of(path)
    lines = run_child(zygote, path.parent / "ack1", map=str(path), mode="compact",
                      crash_at=point)
    assert lines == ["ready"]
    published = point in {"compact.published", "compact.old_partly_removed"}
    assert (path / CURRENT_NAME).exists() == published
    with MapStore.open(path, readonly=True) as store:
        report = check_map(store)
        vertices = store.stats()["vertices"]
        removed_left = store.removed_vertices()
    assert report.ok, report.violations
    # new: renumbered densely, nothing removed left; old: the removed ranges still recorded
    assert (vertices, removed_left) == ((4 * LENGTH, 0) if published else (total, 2 * LENGTH))
    assert state_of(path) == expected
    assert set(expected["sequences"]).isdisjoint(REMOVED)
    assert any("not the live generation" in n for n in report.notes), report.notes

    with MapStore.open(path) as store:  # the writer's open removes the other generation
        assert any("no longer the live generation" in r for r in store.recovery)
    strictly_ok(path)
    lines = run_child(zygote, path.parent / "ack2", map=str(path), mode="compact")
    assert lines[-1] == "done"
    assert state_of(path) == expected
    strictly_ok(path)
    live = sorted(p.name for p in path.iterdir())
    assert live == ["CURRENT", "LOCK", lines[1].split()[1]]
    worker.assert_search_finds_everything(path)


# --- unmerge ----------------------------------------------------------------------------------

UNMERGED = 6


@pytest.fixture
def seven(six):
    """``six`` (edges 2-0, 3-0, 4-1) plus drive 6, which matched drives 0 and 2 both ways and
    added an edge between drives 1 and 5, their only link: unmerging it splits two
    components, {0, 2, 3, 6} and {1, 4, 5}, into {0, 2, 3}, {6}, {1, 4} and {5}."""
    rows = np.random.default_rng(6).standard_normal((LENGTH, 8)).astype(np.float32)
    with MapStore.open(six) as store:
        store.add_sequence(rows, name="d6", edges=[
            EdgeSpec((None, 0), (0, 5), 0.9, 0), EdgeSpec((0, 5), (None, 0), 0.9, 0),
            EdgeSpec((None, 3), (2, 1), 0.8, 3), EdgeSpec((2, 1), (None, 3), 0.8, 3),
            EdgeSpec((1, 2), (5, 3), 0.7)])
    return six


def unmerged(state: dict[str, Any], seq: int) -> dict[str, Any]:
    """``state`` without the edges ``seq`` added (the components: those of the edges left,
    which ``logical_state`` checks itself)."""
    return {"sequences": state["sequences"], "edges": {e for e in state["edges"] if e[3] != seq}}


@pytest.mark.parametrize("point", UNMERGE_POINTS)
def test_kill_at_each_unmerge_point(seven, zygote, point):
    """Killed while unmerging: all of it or none of it, check passing; an unmerge run again
    completes (or finds nothing left to revoke)."""
    path = seven
    before = state_of(path)
    assert before["components"] == {frozenset({0, 2, 3, 6}), frozenset({1, 4, 5})}
    lines = run_child(zygote, path.parent / "ack1", map=str(path), mode="unmerge",
                      seq=UNMERGED, crash_at=point)
    assert lines == ["ready"]
    after = state_of(path)
    committed = point == "unmerge.committed"
    if committed:
        assert {k: after[k] for k in ("sequences", "edges")} == unmerged(before, UNMERGED)
        assert after["components"] == {frozenset({0, 2, 3}), frozenset({6}),
                                       frozenset({1, 4}), frozenset({5})}
        assert after["stats"]["edges"] == before["stats"]["edges"] - 5
    else:
        assert after == before
    strictly_ok(path)
    lines = run_child(zygote, path.parent / "ack2", map=str(path), mode="unmerge",
                      seq=UNMERGED)
    assert lines == ["ready", f"unmerged {0 if committed else 5}", "done"]
    assert {k: state_of(path)[k] for k in ("sequences", "edges")} == unmerged(before, UNMERGED)
    strictly_ok(path)


def test_random_kills_during_unmerge(tmp_path, zygote):
    """Unmerges killed at random instants, 30 times (the delay calibrated on a copy, so kills
    land on both sides of the commit): after each kill the map means exactly what it meant
    before the unmerge or after it (every sequence bit for bit, the edges with their
    provenance, the components of the edges) and passes ``check``; every other kill a
    writer's open leaves it strictly clean. A map whose drives have no edge left is replaced."""
    rng = np.random.default_rng(17)
    kills, outcomes, maps = 0, {"before": 0, "after": 0}, 0
    while kills < 30:
        maps += 1
        path = tmp_path / f"unmerge-map-{maps}"
        create_map(path, dim=8, shard_rows=64)
        with MapStore.open(path) as store:
            for i in range(12):
                worker.add_planned(store, SEED + maps, i, 20)
        acks = tmp_path / "acks"
        copy = tmp_path / "copy"  # calibrate: how long a whole unmerge takes here
        shutil.copytree(path, copy)
        seq = max(range(12), key=lambda s: sum(e[3] == s for e in state_of(copy)["edges"]))
        acks.unlink(missing_ok=True)
        pid = zygote.spawn(map=str(copy), mode="unmerge", seq=seq, ack=str(acks))
        worker.wait_for_line(acks, "ready")
        begun = time.monotonic()
        worker.wait_for_line(acks, "done")
        max_wait = 1.2 * (time.monotonic() - begun)
        zygote.wait(pid)
        shutil.rmtree(copy)
        while kills < 30:
            before = state_of(path)
            left = sorted({e[3] for e in before["edges"]})
            if not left:
                break
            seq = int(rng.choice(left))
            acks.unlink(missing_ok=True)
            pid = zygote.spawn(map=str(path), mode="unmerge", seq=seq, ack=str(acks))
            worker.wait_for_line(acks, "ready")
            time.sleep(rng.uniform(0, max_wait))
            os.kill(pid, signal.SIGKILL)
            status = zygote.wait(pid)
            kills += 1
            if status["signal"] != signal.SIGKILL:  # it finished first
                assert status == {"signal": None, "code": 0}, zygote.log.read_text()
            with MapStore.open(path, readonly=True) as store:
                report = check_map(store)
            assert report.ok, report.violations
            after = state_of(path)
            if after == before:
                outcomes["before"] += 1
            else:
                assert {k: after[k] for k in ("sequences", "edges")} == unmerged(before, seq)
                outcomes["after"] += 1
            if kills % 2:
                MapStore.open(path).close()
                strictly_ok(path)
        acks.unlink(missing_ok=True)
    print({"kills": kills, "maps": maps, **outcomes})
    assert sum(outcomes.values()) == kills == 30


# --- (b) random kills -------------------------------------------------------------------------


def test_random_kills(tmp_path, zygote):
    stats = worker.kill_loop(tmp_path, zygote, kills=200, seed=11)
    print(stats.to_dict())
    assert stats.kills == 200 and not stats.violations


@pytest.mark.slow
def test_random_kills_longer_writes(tmp_path, zygote):
    """Fewer, longer-lived writers: larger maps, more index publications per writer (one map
    taken to 50 kills, a second to 10; ``tools/crash_soak.py`` runs thousands)."""
    stats = worker.kill_loop(tmp_path, zygote, kills=60, seed=12, kills_per_map=50,
                             max_wait=0.25)
    print(stats.to_dict())
    assert stats.kills == 60 and stats.maps == 2 and not stats.violations


# --- readers beside a writer ----------------------------------------------------------------


def test_readers_see_consistent_snapshots_while_a_writer_adds(tmp_path, zygote):
    """Read-only opens in this process while another process commits: every snapshot is a
    complete prefix of the stream, and a search sees every committed row."""
    path, seed = tmp_path / "m", 5
    create_map(path, **worker.KILL_MAP)
    acks = tmp_path / "acks"
    pid = zygote.spawn(map=str(path), seed=seed, ack=str(acks))
    try:
        worker.wait_for_line(acks, "ready")
        seen = []
        acked_at_start = len(worker.read_acks(acks))
        deadline = time.monotonic() + 120
        # Keep reading until the writer has committed more since the first read, so reads and
        # writes did interleave (no timing assumption: only a hang trips the deadline).
        while len(seen) < 10 or len(worker.read_acks(acks)) <= acked_at_start + 5:
            assert time.monotonic() < deadline, "writer made no progress"
            before = worker.read_acks(acks)
            with MapStore.open(path, readonly=True) as store:
                n = store.stats()["sequences"]
                if n:
                    last = store.sequences()[-1]
                    rows = store.descriptors(last.seq_id)
                    _, ids = store.search(np.asarray(rows), k=1)
                    np.testing.assert_array_equal(
                        ids[:, 0], np.arange(last.first_vertex, last.first_vertex + last.length))
            verify_snapshot_prefix(path, seed)
            assert before <= set(range(n))
            seen.append(n)
        assert seen == sorted(seen)
    finally:
        os.kill(pid, signal.SIGKILL)
        zygote.wait(pid)
    worker.assert_ok_but_partials(verify(path, seed, worker.read_acks(acks)))


def verify_snapshot_prefix(path: Path, seed: int) -> None:
    """The data half of :func:`verify` (``check`` is not meant for a map being written)."""
    with MapStore.open(path, readonly=True) as store:
        dim = store.config.dim
        first = 0
        for i, rec in enumerate(store.sequences()):
            plan = worker.planned(seed, i, dim, None)
            assert (rec.name, rec.first_vertex, rec.length) == (
                plan.name, first, len(plan.descriptors))
            assert store.descriptors(i).tobytes() == plan.descriptors.tobytes()
            first += rec.length


def test_random_kills_during_compaction(tmp_path, zygote):
    """Compactions killed at random instants, 30 times (``compact_kill_loop``; soak size:
    ``tools/compact_soak.py``): after every kill the old or the new map, meaning exactly what it
    meant (every live sequence bit for bit, the removed ones absent, the components of the
    edges), ``check`` passing; a writer's open cleans up to a strict ``check``."""
    stats = worker.compact_kill_loop(tmp_path, zygote, kills=30, seed=13, kills_per_map=15)
    print(stats.to_dict())
    assert stats.kills == 30 and not stats.violations
