"""Several drives in one ingest (sprint_map/merge/drives.py): equal to serial ingest, each atomic.

The crash test kills a real ``sprint-map ingest A B C`` between two drives of one group.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sprint_map import Drive, MapConfig, SprintMap
from sprint_map.config import StoreOptions
from sprint_map.errors import DuplicateNameError, InputError, InvalidDescriptorError
from sprint_map.testing.crash import CRASH_ENV, GROUP_POINTS

DIM = 16


@pytest.fixture
def drives(rng):
    """Four noisy drives over 80 places (the second half of the last one is new)."""
    places = rng.standard_normal((120, DIM))
    out = []
    for i in range(4):
        x = places[:80] + 0.3 * rng.standard_normal((80, DIM))
        if i == 3:
            x[40:] = places[80:] + 0.3 * rng.standard_normal((40, DIM))
        out.append((x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32))
    return out


def snapshot(path: Path) -> dict[str, object]:
    """What a map holds: sequences (with rows), edges with provenance, components."""
    with SprintMap.open(path, readonly=True) as m:
        seqs = [(s.seq_id, s.name, s.length, m.descriptors(s.seq_id).tobytes())
                for s in m.sequences()]
        edges = [(e.to_dict(), e.frame) for e in m.edges()]
        comps = [(c.component, c.sequences, c.vertices) for c in m.components()]
        assert m.check().ok
    return {"sequences": seqs, "edges": edges, "components": comps}


@pytest.mark.parametrize("group_drives", [1, 2, 16])
def test_one_call_equals_serial_ingest(tmp_path, drives, group_drives):
    serial, grouped = tmp_path / "serial", tmp_path / "grouped"
    with SprintMap.create(serial, MapConfig(dim=DIM)) as m:
        expected = [m.ingest(d, name=f"d{i}", source=f"s{i}") for i, d in enumerate(drives)]
    seen: list[list[str]] = []
    with SprintMap.create(grouped, MapConfig(dim=DIM)) as m:
        results = m.ingest_drives(
            [Drive(iter([d[:50], d[50:]]), f"d{i}", None, f"s{i}") for i, d in enumerate(drives)],
            group_drives=group_drives,
            on_committed=lambda group: seen.append([r.added.sequence.name for r in group]))
    assert [r.to_dict()["decisions"] for r in results] == \
        [r.to_dict()["decisions"] for r in expected]
    assert sum(r.added.edges_added for r in results) > 0
    assert snapshot(grouped) == snapshot(serial)
    names = [f"d{i}" for i in range(4)]
    assert seen == [names[i : i + group_drives] for i in range(0, 4, group_drives)]


def test_duplicate_names_refused_before_any_write(tmp_path, drives):
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        with pytest.raises(InputError, match="'a'"):
            m.ingest_drives([Drive(drives[0], "a"), Drive(drives[1], "b"), Drive(drives[2], "a")])
        with pytest.raises(InputError, match="group_drives"):
            m.ingest_drives([Drive(drives[0], "a")], group_drives=0)
        assert m.stats()["sequences"] == 0


def test_failed_drive_leaves_earlier_committed_and_later_absent(tmp_path, drives):
    bad = drives[1].copy()
    bad[70] = np.nan
    reported: list[str] = []
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        with pytest.raises(InvalidDescriptorError):
            m.ingest_drives([Drive(drives[0], "a"), Drive(bad, "b"), Drive(drives[2], "c")],
                            on_committed=lambda g: reported.extend(r.added.sequence.name
                                                                   for r in g))
        assert [s.name for s in m.sequences()] == ["a"]
        assert m.stats()["vertices"] == 80
    assert reported == ["a"]
    assert snapshot(tmp_path / "m")["sequences"][0][1] == "a"


def test_group_defers_the_index_persist_to_its_end(tmp_path, drives):
    config = MapConfig(dim=DIM, store=StoreOptions(index_persist_every=1, index_persist_growth=0))
    with SprintMap.create(tmp_path / "m", config) as m:
        files = []
        with m.store.group_commit():
            for i, d in enumerate(drives[:2]):
                m.ingest(d, name=f"d{i}", merge=False)
                files.append(sorted(p.name for p in (m.store.data_path / "index").iterdir()))
        after = sorted(p.name for p in (m.store.data_path / "index").iterdir())
    assert files[0] == files[1]  # nothing persisted inside the group
    assert after != files[1] and any("000000000160" in name for name in after)


CLI = [sys.executable, "-c", "from sprint_map.cli.main import main; main()"]


def test_crash_between_drives_keeps_the_earlier_ones(tmp_path, drives):
    """A real ``ingest A B C`` SIGKILLed between A and B: A is committed, B and C absent, the
    map passes check; running the command again completes it as serial ingest would."""
    sources = []
    for i, d in enumerate(drives[:3]):
        sources.append(tmp_path / f"d{i}.npy")
        np.save(sources[-1], d)
    path = tmp_path / "m"
    with SprintMap.create(path, MapConfig(dim=DIM)):
        pass
    env = {**os.environ, CRASH_ENV: "group.between_drives"}
    proc = subprocess.run([*CLI, "ingest", str(path), *map(str, sources)], env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    state = snapshot(path)
    assert [s[1] for s in state["sequences"]] == ["d0"]  # type: ignore[index]
    again = subprocess.run([*CLI, "ingest", str(path), *map(str, sources), "--json"],
                           capture_output=True, text=True, timeout=120)
    assert again.returncode == 0, again.stderr
    out = json.loads(again.stdout)
    assert [(r["name"], r["already_committed"]) for r in out] == \
        [("d0", True), ("d1", False), ("d2", False)]
    serial = tmp_path / "serial"
    with SprintMap.create(serial, MapConfig(dim=DIM)) as m:
        for i, d in enumerate(drives[:3]):
            m.ingest(d, name=f"d{i}", source=str(sources[i]))
    assert snapshot(path) == snapshot(serial)
    assert "group.between_drives" in GROUP_POINTS


# --- appended drives: one group commit -------------------------------------------------------


def append_serially(path: Path, drives: list[np.ndarray], names: list[str]) -> None:
    with SprintMap.create(path, MapConfig(dim=DIM, store=StoreOptions(shard_rows=100))) as m:
        for d, name in zip(drives, names, strict=True):
            m.ingest(d, name=name, merge=False, source=name)


@pytest.mark.parametrize("group_drives", [1, 3, 16])
def test_appended_drives_equal_serial_appends_in_one_transaction(tmp_path, drives,
                                                                 group_drives):
    names = [f"d{i}" for i in range(4)]
    append_serially(tmp_path / "serial", drives, names)
    with SprintMap.create(tmp_path / "grouped", MapConfig(dim=DIM, store=StoreOptions(shard_rows=100))) as m:
        txn_before = m.store.env.env.info()["last_txnid"]
        results = m.ingest_drives(
            [Drive(d if i % 2 else iter([d[:30], d[30:]]), n, None, n)
             for i, (d, n) in enumerate(zip(drives, names, strict=True))],
            merge=False, group_drives=group_drives)
        transactions = m.store.env.env.info()["last_txnid"] - txn_before
    assert transactions == -(-4 // group_drives)  # one LMDB transaction per group
    assert [r.added.sequence.name for r in results] == names
    assert [r.added.sequence.first_vertex for r in results] == [0, 80, 160, 240]
    assert all(r.decisions == [] and r.added.edges_added == 0 for r in results)
    assert snapshot(tmp_path / "grouped") == snapshot(tmp_path / "serial")


def test_a_failing_appended_drive_commits_the_ones_before_it(tmp_path, drives):
    """Drive c's stream fails midway (its rows crossed into a new shard file): a and b are
    committed in the group's transaction, c's rows are truncated, d is never begun."""
    def broken():
        yield drives[2][:50]
        bad = drives[2][50:].copy()
        bad[5] = np.inf
        yield bad

    reported: list[list[str]] = []
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM, store=StoreOptions(shard_rows=100))) as m:
        with pytest.raises(InvalidDescriptorError, match="frame 55"):
            m.ingest_drives([Drive(drives[0], "a"), Drive(drives[1], "b"),
                             Drive(broken(), "c"), Drive(drives[3], "d")], merge=False,
                            on_committed=lambda g: reported.append(
                                [r.added.sequence.name for r in g]))
        assert [s.name for s in m.sequences()] == ["a", "b"]
        m.ingest(drives[3], name="d", merge=False)  # the writer goes on after the failure
    assert reported == [["a", "b"]]
    state = snapshot(tmp_path / "m")
    assert [s[1] for s in state["sequences"]] == ["a", "b", "d"]  # type: ignore[index]
    append_serially(tmp_path / "serial", [drives[0], drives[1], drives[3]], ["a", "b", "d"])
    assert [s[1:] for s in state["sequences"]] == [  # type: ignore[attr-defined]
        s[1:] for s in snapshot(tmp_path / "serial")["sequences"]]  # type: ignore[attr-defined]


def test_an_appended_retry_is_recognised_inside_a_group(tmp_path, drives):
    with SprintMap.create(tmp_path / "m", MapConfig(dim=DIM)) as m:
        m.ingest(drives[0], name="a", merge=False)
        results = m.ingest_drives([Drive(drives[0], "a"), Drive(drives[1], "b")], merge=False)
        assert [(r.added.sequence.seq_id, r.added.already_committed) for r in results] == \
            [(0, True), (1, False)]
        with pytest.raises(DuplicateNameError, match="'b'"):
            m.ingest_drives([Drive(drives[2], "c"), Drive(drives[2], "b")], merge=False)
        assert [s.name for s in m.sequences()] == ["a", "b", "c"]


def cli_sources(tmp_path: Path, drives: list[np.ndarray]) -> list[Path]:
    sources = []
    for i, d in enumerate(drives):
        sources.append(tmp_path / f"d{i}.npy")
        np.save(sources[-1], d)
    return sources


#: Where a kill inside one ``ingest --no-merge`` group leaves it: all of the group or none.
GROUP_COMMITTED = {"group.between_drives": False, "group.rows_written": False,
                   "group.before_commit": False, "add.before_commit": False,
                   "group.committed": True}


@pytest.mark.parametrize("point", sorted(GROUP_COMMITTED))
def test_kill_inside_an_appended_group(tmp_path, drives, point):
    """A real ``ingest MAP A B C --no-merge`` SIGKILLed at each point of its group commit: the
    map passes check with the earlier drive (d0, its own command) and either the whole group
    or none of it; the rows past the commit are truncated by the next writer's open, and the
    same command run again completes the map as serial appends would."""
    sources = cli_sources(tmp_path, drives)
    path = tmp_path / "m"
    with SprintMap.create(path, MapConfig(dim=DIM, store=StoreOptions(shard_rows=100))):
        pass
    first = subprocess.run([*CLI, "ingest", str(path), str(sources[0]), "--no-merge"],
                           capture_output=True, text=True, timeout=120)
    assert first.returncode == 0, first.stderr
    command = [*CLI, "ingest", str(path), *map(str, sources[1:]), "--no-merge"]
    proc = subprocess.run(command, env={**os.environ, CRASH_ENV: point},
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    with SprintMap.open(path, readonly=True) as m:
        report = m.check()
        assert report.ok, report.violations
        tail = any("uncommitted" in note for note in report.notes)
        names = [s.name for s in m.sequences()]
    assert names == (["d0", "d1", "d2", "d3"] if GROUP_COMMITTED[point] else ["d0"])
    assert tail == (point != "group.committed")  # the group's rows, past the committed end
    with SprintMap.open(path) as m:  # the next writer's open truncates them
        assert bool(m.store.recovery) == tail
    again = subprocess.run([*command, "--json"], capture_output=True, text=True, timeout=120)
    assert again.returncode == 0, again.stderr
    assert [(r["name"], r["already_committed"]) for r in json.loads(again.stdout)] == \
        [(f"d{i}", GROUP_COMMITTED[point]) for i in (1, 2, 3)]
    assert [(r["frames"], r["frames_stored"]) for r in json.loads(again.stdout)] == \
        [(len(drives[i]), len(drives[i])) for i in (1, 2, 3)]
    state = snapshot(path)
    append_serially(tmp_path / "serial", drives, [f"d{i}" for i in range(4)])
    assert [s[1:] for s in state["sequences"]] == [  # type: ignore[attr-defined]
        s[1:] for s in snapshot(tmp_path / "serial")["sequences"]]  # type: ignore[attr-defined]
