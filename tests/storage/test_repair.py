"""Torn tails, torn or stale index files, temp files: a writer's open recovers them, and
``check --repair`` fixes them on a map no writer reopened. ``check --repair`` against every
corruption of ``test_check.py``: the derivable ones repaired, the others reported.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.errors import MapLockedError
from sprint_map.storage.check import REPAIRABLE, check_map
from sprint_map.storage.index.map_index import index_files
from sprint_map.storage.keys import u64
from sprint_map.storage.lock import WriterLock
from sprint_map.storage.repair import repair_map
from sprint_map.storage.store import INDEX_DIR, SHARDS_DIR, MapStore
from tests.storage import test_check as corruptions

TOTAL = corruptions.TOTAL  # 42 vertices; shard_rows 16: shards 0 and 1 sealed, 2 holds 10 rows
ROW = 8 * 4  # bytes per row (dim 8)


@pytest.fixture
def base(make_map):
    """The healthy map of ``test_check.py``, its index persisted at 42 vertices."""
    built = make_map(corruptions.LENGTHS, dim=8, shard_rows=16, edges=1)
    with MapStore.open(built.path) as store:
        store.search(built.all_descriptors()[:1], k=1)  # load the index; close persists it
    return built


def shard(path: Path, n: int) -> Path:
    return path / SHARDS_DIR / f"shard-{n:06d}.f32"


def append(file: Path, data: bytes) -> None:
    with file.open("ab") as f:
        f.write(data)


def the_index(path: Path) -> Path:
    (_, file), = index_files(path / INDEX_DIR)
    return file


# --- torn tails and leftovers: what a crash (or a torn power loss) can leave ------------------


def torn_append_open_shard(path: Path) -> None:
    """A kill mid-append: two and a half uncommitted rows after the open shard's 10."""
    append(shard(path, 2), os.urandom(2 * ROW + ROW // 2))


def torn_append_into_new_shard(path: Path) -> None:
    """The open shard filled up and half a row in a new shard."""
    append(shard(path, 2), os.urandom(6 * ROW))
    shard(path, 3).write_bytes(os.urandom(ROW // 2))


def garbage_past_open_shard(path: Path) -> None:
    append(shard(path, 2), b"\xff" * 100)


def garbage_past_sealed_shard(path: Path) -> None:
    """Only check --repair truncates a sealed shard (a writer's open touches the open one)."""
    append(shard(path, 0), b"\xff" * 37)


def index_cut_short(path: Path) -> None:
    file = the_index(path)
    os.truncate(file, file.stat().st_size // 2)


def index_with_garbage_appended(path: Path) -> None:
    append(the_index(path), b"\x00" * 64)


def index_ahead_of_lmdb(path: Path) -> None:
    file = the_index(path)
    file.rename(file.with_name(f"flat.{TOTAL + 8:012d}.faiss"))


def temp_files_everywhere(path: Path) -> None:
    """Leftovers of interrupted publications, one of them a torn copy of the index."""
    file = the_index(path)
    file.with_name(file.name + ".partial").write_bytes(file.read_bytes()[:100])
    (path / SHARDS_DIR / "shard-000002.f32.partial").write_bytes(b"x")
    (path / "config.partial").write_bytes(b"")


TORN = [
    torn_append_open_shard,
    torn_append_into_new_shard,
    garbage_past_open_shard,
    garbage_past_sealed_shard,
    index_cut_short,
    index_with_garbage_appended,
    index_ahead_of_lmdb,
    temp_files_everywhere,
]


def check(path: Path):
    with MapStore.open(path, readonly=True) as store:
        return check_map(store)


def assert_intact(path: Path, built, expect_map) -> None:
    """Everything committed is there bit for bit, and a search finds every row."""
    with MapStore.open(path, readonly=True) as store:
        expect_map(store, built)
        _, ids = store.search(built.all_descriptors(), k=1)
    np.testing.assert_array_equal(ids[:, 0], np.arange(TOTAL))


@pytest.mark.parametrize("corrupt", TORN, ids=lambda f: f.__name__)
def test_writable_open_recovers(base, corrupt, expect_map):
    corrupt(base.path)
    with MapStore.open(base.path) as store:
        assert store.recovery or corrupt is garbage_past_sealed_shard
    report = check(base.path)
    assert report.ok, report.violations
    if corrupt is garbage_past_sealed_shard:
        assert report.notes == ["shard-000000.f32 has 37 uncommitted bytes (truncated by check "
                                "--repair)"]
    assert_intact(base.path, base, expect_map)
    assert check(base.path).ok  # the search above loaded (and a reader never writes) the index


@pytest.mark.parametrize("corrupt", TORN, ids=lambda f: f.__name__)
def test_repair_fixes_a_map_no_writer_reopened(base, corrupt, expect_map):
    corrupt(base.path)
    before = check(base.path)
    assert not before.ok or before.notes
    fixed = repair_map(base.path)
    assert fixed.ok, fixed.to_dict()
    assert fixed.repaired and not fixed.skipped
    assert not fixed.after.notes, fixed.after.notes
    assert_intact(base.path, base, expect_map)
    assert repair_map(base.path).repaired == []  # converged


def test_repair_of_a_healthy_map_changes_nothing(base, expect_map):
    files = {p: p.read_bytes() for p in sorted(base.path.rglob("*")) if p.is_file()
             and p.parent.name != "map.lmdb" and p.name != "LOCK"}
    fixed = repair_map(base.path)
    assert fixed.ok and fixed.repaired == [] and fixed.skipped == []
    assert {p: p.read_bytes() for p in files} == files
    assert_intact(base.path, base, expect_map)


# --- every corruption check catches ------------------------------------------------------------

DERIVABLE = {
    "missing_reverse_edge",
    "wrong_edge_counter",
    "union_find_split",
    "union_find_cycle",
    "wrong_component_totals",
    "index_renamed_ahead",
    "index_ahead_after_lmdb_rollback",
    "index_wrong_stamp",
}
NOT_DERIVABLE = {
    # The shard is the data and its sequence's content digest says it changed: not rebuilt
    # into the index either (the index then holds the only intact copy of the row).
    "flip_shard_row",
    "delete_sealed_shard",  # committed rows exist nowhere else (but in the index cache)
    "delete_open_shard",
    "truncate_shard",
    "dangling_edge",  # which vertex was meant is lost
    "edge_inside_a_sequence",
}


def test_every_corruption_is_classified():
    assert {f.__name__ for f in corruptions.CORRUPTIONS} == DERIVABLE | NOT_DERIVABLE


@pytest.mark.parametrize("corrupt", corruptions.CORRUPTIONS, ids=lambda f: f.__name__)
def test_repair_fixes_what_is_derivable_and_reports_the_rest(base, corrupt, expect_map):
    expected = corrupt(base.path)
    fixed = repair_map(base.path)
    if corrupt.__name__ in DERIVABLE:
        assert fixed.ok, fixed.to_dict()
        assert fixed.repaired
        with MapStore.open(base.path, readonly=True) as store:
            if corrupt.__name__ != "flip_shard_row":  # there the shard row itself changed
                expect_map(store, base)
            rows = np.array(store.shards.rows(0, TOTAL, TOTAL))
            _, ids = store.search(rows, k=1)
        np.testing.assert_array_equal(ids[:, 0], np.arange(TOTAL))
    else:
        assert not fixed.ok
        assert any(expected in v for v in fixed.after.violations), fixed.after.violations
        # Whatever was derivable around it was still repaired (but an index that holds the
        # only intact copy of a changed shard row).
        kept = {"index"} if corrupt.__name__ == "flip_shard_row" else set()
        assert fixed.after.areas & REPAIRABLE == kept, fixed.after.violations
    assert repair_map(base.path).repaired == []  # converged


def test_repair_touches_nothing_when_the_sequences_do_not_tile(base):
    with MapStore.open(base.path) as store:
        store.env.write(lambda txn: txn.put(b"n_sequences", u64(7), db=store.env.db("meta")))
        store.env.write(lambda txn: txn.delete(b"\x00\x00\x00\x01",
                                               db=store.env.db("sequences")))
    append(shard(base.path, 0), b"\xff" * 5)
    fixed = repair_map(base.path)
    assert not fixed.ok and fixed.repaired == []
    assert fixed.skipped == ["nothing touched: the sequence records do not tile the vertex ids, "
                             "and every derived record and file length depends on them"]
    assert "sequences" in fixed.after.areas
    assert shard(base.path, 0).stat().st_size == 16 * ROW + 5  # not even a tail was cut


def test_repair_does_not_even_open_for_writing_when_next_vertex_id_is_wrong(base):
    """A writer's open would truncate the open shard at the wrong length: committed rows."""
    size = shard(base.path, 2).stat().st_size
    with MapStore.open(base.path) as store:
        store.env.write(lambda txn: txn.put(b"next_vertex_id", u64(TOTAL - 3),
                                            db=store.env.db("meta")))
    fixed = repair_map(base.path)
    assert not fixed.ok and fixed.repaired == [] and fixed.skipped
    assert f"sequences cover {TOTAL} vertices but meta says {TOTAL - 3}" in fixed.found
    assert shard(base.path, 2).stat().st_size == size


def test_repair_needs_the_writer_lock(base):
    lock = WriterLock(base.path)  # as a writer in another process holds it
    lock.acquire()
    try:
        with pytest.raises(MapLockedError):
            repair_map(base.path)
    finally:
        lock.release()


# --- the command --------------------------------------------------------------------------------


def run_check(*args: str) -> tuple[int, str]:
    result = CliRunner().invoke(main, ["check", *args])
    assert "Traceback" not in result.output
    return result.exit_code, result.output


@pytest.mark.parametrize(("corrupt", "found"), [(corruptions.union_find_cycle, 1),
                                               (index_cut_short, 1),
                                               (temp_files_everywhere, 0)],  # (notes: exit 0)
                         ids=lambda f: getattr(f, "__name__", str(f)))
def test_cli_check_repair_exits_0_when_healthy_again(base, corrupt: Callable[[Path], object],
                                                     found: int):
    corrupt(base.path)
    assert run_check(str(base.path))[0] == found
    code, output = run_check(str(base.path), "--repair")
    assert code == 0, output
    lines = output.strip().splitlines()
    assert lines[0].startswith("repaired: ") and lines[-1] == f"ok ({len(lines) - 1} repaired)"
    assert run_check(str(base.path)) == (0, "ok\n")


def test_cli_check_repair_reports_what_it_cannot(base):
    corruptions.dangling_edge(base.path)
    code, output = run_check(str(base.path), "--repair")
    assert code == 1
    assert "repaired: rebuilt the reverse index of" in output
    assert output.strip().splitlines()[-1] == "1 violation(s) left after repair (edges)"
    code, output = run_check(str(base.path), "--repair", "--json")
    data = json.loads(output)
    assert code == 1 and not data["ok"] and data["repaired"] == []
    assert data["unrepaired"] == [f"edge 3 -> {TOTAL + 5} has an endpoint outside the map's "
                                  f"{TOTAL} vertices"]
