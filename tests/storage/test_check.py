"""``check_map`` catches each deliberate corruption; a writable open repairs the repairable ones."""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import lmdb
import numpy as np
import pytest

from sprint_map.storage.check import check_map
from sprint_map.storage.index.map_index import index_files
from sprint_map.storage.keys import EDGE_KEY, EDGE_VAL, UF_VAL, u32, u64
from sprint_map.storage.lmdb_env import MAX_DBS
from sprint_map.storage.store import INDEX_DIR, LMDB_DIR, SHARDS_DIR, MapStore

LENGTHS = (10, 7, 20, 5)  # 42 vertices; shard_rows=16: shards 0 and 1 sealed, shard 2 holds 10
TOTAL = sum(LENGTHS)


@contextmanager
def raw_lmdb(path: Path) -> Iterator[tuple[lmdb.Transaction, Callable[[str], object]]]:
    """A write transaction on the map's LMDB with the plain lmdb module (no sprint-map code)."""
    env = lmdb.open(str(path / LMDB_DIR), max_dbs=MAX_DBS)
    try:
        with env.begin(write=True) as txn:
            yield txn, lambda name: env.open_db(name.encode(), txn=txn, create=False)
    finally:
        env.close()


def report_of(path: Path):
    with MapStore.open(path, readonly=True) as store:
        return check_map(store)


@pytest.fixture
def base(make_map):
    """A healthy, connected map whose index was persisted at 42 vertices."""
    built = make_map(LENGTHS, dim=8, shard_rows=16, edges=1)
    with MapStore.open(built.path) as store:
        store.search(built.all_descriptors()[:1], k=1)  # load the index; close persists it
    assert [u for u, _ in index_files(built.path / INDEX_DIR)] == [TOTAL]
    return built


def shard(path: Path, n: int) -> Path:
    return path / SHARDS_DIR / f"shard-{n:06d}.f32"


# --- corruptions: each returns a fragment of the violation it must cause --------------------


def delete_sealed_shard(path: Path) -> str:
    shard(path, 1).unlink()
    return "shard-000001.f32 is missing"


def delete_open_shard(path: Path) -> str:
    shard(path, 2).unlink()
    return "shard-000002.f32 is missing"


def truncate_shard(path: Path) -> str:
    file = shard(path, 0)
    with file.open("r+b") as f:
        f.truncate(file.stat().st_size - 4)
    return "shard-000000.f32 is truncated"


def flip_shard_row(path: Path) -> str:
    """Row 0 changed after the index was built (the check compares vertex 0 always)."""
    file = shard(path, 0)
    data = bytearray(file.read_bytes())
    data[0] ^= 0x40
    file.write_bytes(bytes(data))
    return "index vector of vertex 0 differs"


def dangling_edge(path: Path) -> str:
    with raw_lmdb(path) as (txn, db):
        txn.put(EDGE_KEY.pack(3, TOTAL + 5), EDGE_VAL.pack(1.0, 0, 0, 0.0), db=db("edges"))
    return f"edge 3 -> {TOTAL + 5} has an endpoint outside"


def edge_inside_a_sequence(path: Path) -> str:
    with raw_lmdb(path) as (txn, db):
        txn.put(EDGE_KEY.pack(0, 1), EDGE_VAL.pack(1.0, 0, 0, 0.0), db=db("edges"))
        txn.put(EDGE_KEY.pack(1, 0), b"", db=db("edges_rev"))
        txn.put(b"n_edges", u64(len(LENGTHS)), db=db("meta"))
    return "lies inside sequence 0"


def missing_reverse_edge(path: Path) -> str:
    with raw_lmdb(path) as (txn, db):
        cursor = txn.cursor(db=db("edges_rev"))
        assert cursor.first()
        cursor.delete()
    return "reverse edge index does not mirror"


def wrong_edge_counter(path: Path) -> str:
    with raw_lmdb(path) as (txn, db):
        txn.put(b"n_edges", u64(99), db=db("meta"))
    return "meta says 99 edges"


def union_find_split(path: Path) -> str:
    """A sequence made its own root although edges join it to the others."""
    with raw_lmdb(path) as (txn, db):
        uf = db("uf")
        victim = next(s for s in range(len(LENGTHS))
                      if UF_VAL.unpack(txn.get(u32(s), db=uf))[0] != s)
        txn.put(u32(victim), UF_VAL.pack(victim, 1), db=uf)
    return "membership lists disagree with union-find"


def union_find_cycle(path: Path) -> str:
    with raw_lmdb(path) as (txn, db):
        uf = db("uf")
        root = next(s for s in range(len(LENGTHS)) if UF_VAL.unpack(txn.get(u32(s), db=uf))[0] == s)
        other = (root + 1) % len(LENGTHS)
        txn.put(u32(root), UF_VAL.pack(other, 4), db=uf)
        txn.put(u32(other), UF_VAL.pack(root, 4), db=uf)
    return "is cyclic or dangling"


def wrong_component_totals(path: Path) -> str:
    with raw_lmdb(path) as (txn, db):
        cursor = txn.cursor(db=db("comp"))
        assert cursor.first()
        cursor.put(cursor.key(), np.array([4, 41], dtype=">u8").tobytes())
    return "totals (4, 41)"


def index_renamed_ahead(path: Path) -> str:
    (_, file), = index_files(path / INDEX_DIR)
    file.rename(file.with_name(f"flat.{TOTAL + 8:012d}.faiss"))
    return f"flat.{TOTAL + 8:012d}.faiss is ahead of the map"


def index_ahead_after_lmdb_rollback(path: Path) -> str:
    """LMDB loses commits the index saw: restore a copy of the LMDB dir taken before them."""
    saved = path.parent / "lmdb-before"
    shutil.copytree(path / LMDB_DIR, saved)
    with MapStore.open(path) as store:
        store.add_sequence(np.ones((9, 8), dtype=np.float32))
        store.search(np.ones((1, 8)), k=1)
    shutil.rmtree(path / LMDB_DIR)
    saved.rename(path / LMDB_DIR)
    return f"flat.{TOTAL + 9:012d}.faiss is ahead of the map"


def partial_in(where: str) -> Callable[[Path], str]:
    def corrupt(path: Path) -> str:
        (path / where / "flat.000000000099.faiss.partial").write_bytes(b"torn")
        return "leftover temp file"

    corrupt.__name__ = f"partial_in_{where or 'root'}"
    return corrupt


def index_wrong_stamp(path: Path) -> str:
    """A file whose name claims fewer vectors than it holds."""
    (_, file), = index_files(path / INDEX_DIR)
    file.rename(file.with_name(f"flat.{TOTAL - 2:012d}.faiss"))
    return f"holds {TOTAL} vectors"


CORRUPTIONS = [
    delete_sealed_shard,
    delete_open_shard,
    truncate_shard,
    flip_shard_row,
    dangling_edge,
    edge_inside_a_sequence,
    missing_reverse_edge,
    wrong_edge_counter,
    union_find_split,
    union_find_cycle,
    wrong_component_totals,
    index_renamed_ahead,
    index_ahead_after_lmdb_rollback,
    index_wrong_stamp,
]

#: Leftovers of interrupted writers: notes, not violations (the map is whole).
LEFTOVERS = [partial_in(INDEX_DIR), partial_in(SHARDS_DIR), partial_in("")]

#: Corruptions a writable open (recovery, then the index cache logic) must undo.
REPAIRABLE = [index_renamed_ahead, index_ahead_after_lmdb_rollback, *LEFTOVERS]


def test_healthy_map_passes(base):
    report = report_of(base.path)
    assert report.ok, report.violations
    assert report.checked["vertices"] == TOTAL
    assert report.checked["index_vectors_compared"] >= 2


@pytest.mark.parametrize("corrupt", CORRUPTIONS, ids=lambda f: f.__name__)
def test_check_catches(base, corrupt):
    expected = corrupt(base.path)
    report = report_of(base.path)
    assert not report.ok
    assert any(expected in v for v in report.violations), report.violations


@pytest.mark.parametrize("leave", LEFTOVERS, ids=lambda f: f.__name__)
def test_a_leftover_temp_file_is_a_note_cleaned_by_the_next_writer(base, leave):
    expected = leave(base.path)
    report = report_of(base.path)
    assert report.ok, report.violations
    assert any(expected in n and "removed by the next writer's open" in n
               for n in report.notes), report.notes
    MapStore.open(base.path).close()
    assert not any(expected in n for n in report_of(base.path).notes)


def test_a_partial_name_that_is_no_file_is_a_violation(base):
    (base.path / INDEX_DIR / "flat.000000000099.faiss.partial").mkdir()
    report = report_of(base.path)
    assert report.areas == {"temp"}
    assert "is not a regular file" in report.violations[0]


@pytest.mark.parametrize("corrupt", REPAIRABLE, ids=lambda f: f.__name__)
def test_writable_open_repairs(base, corrupt, expect_map):
    corrupt(base.path)
    MapStore.open(base.path).close()
    report = report_of(base.path)
    assert report.ok, report.violations
    with MapStore.open(base.path, readonly=True) as store:
        expect_map(store, base)
        _, ids = store.search(base.all_descriptors(), k=1)
    np.testing.assert_array_equal(ids[:, 0], np.arange(TOTAL))


@pytest.mark.parametrize("extra_shard", [False, True], ids=["tail", "tail+next-shard"])
def test_shard_tail_garbage_is_a_note_and_truncated_by_a_writer(base, extra_shard):
    with shard(base.path, 2).open("ab") as f:
        f.write(b"\x7f" * 100)
    if extra_shard:
        shard(base.path, 3).write_bytes(b"\x01" * 64)
    report = report_of(base.path)
    assert report.ok, report.violations
    assert any("shard-000002.f32 has 100 uncommitted bytes" in n for n in report.notes)
    with MapStore.open(base.path) as store:
        assert any("truncated shard-000002.f32 to 10" in a for a in store.recovery)
    assert shard(base.path, 2).stat().st_size == 10 * 8 * 4
    assert not shard(base.path, 3).exists()
    report = report_of(base.path)
    assert report.ok and not report.notes, (report.violations, report.notes)


def test_stale_index_from_lost_commits_is_never_trusted(base, rng):
    """After an LMDB rollback, new commits reach the stale file's stamp with other content.

    The writer's open must have discarded the stale file, or the search below would return
    vectors that are not in the map.
    """
    index_ahead_after_lmdb_rollback(base.path)  # stale file stamped TOTAL + 9
    fresh = rng.standard_normal((9, 8)).astype(np.float32)
    with MapStore.open(base.path) as store:
        store.add_sequence(fresh)
    with MapStore.open(base.path, readonly=True) as store:
        assert check_map(store).ok
        distances, ids = store.search(fresh, k=1)
    np.testing.assert_array_equal(ids[:, 0], np.arange(TOTAL, TOTAL + 9))
    assert (distances[:, 0] == 0).all()
