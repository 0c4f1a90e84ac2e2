"""Refusals: each bad call raises its own error class and leaves the map exactly as it was."""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import lmdb
import numpy as np
import pytest

from sprint_map.config import SCHEMA_VERSION, MapConfig, StoreOptions
from sprint_map.errors import (
    DescriptorShapeError,
    DuplicateNameError,
    EmptySequenceError,
    InputError,
    InvalidDescriptorError,
    MapExistsError,
    MapLockedError,
    NotAMapError,
    ReadOnlyMapError,
    SchemaVersionError,
    StorageIOError,
    UnknownSequenceError,
)
from sprint_map.storage.lmdb_env import DB_NAMES, MAX_DBS
from sprint_map.storage.lock import LOCK_NAME
from sprint_map.storage.records import EdgeSpec
from sprint_map.storage.store import INDEX_DIR, LMDB_DIR, SHARDS_DIR, MapStore
from tests.helpers import crash_worker

WORKER = Path(crash_worker.__file__)
DIM = 4


def snapshot(store: MapStore) -> dict[str, object]:
    """Everything a failed add could have touched: every LMDB record and every shard byte."""
    with store.env.read() as txn:
        records = {
            name: list(txn.cursor(db=store.env.db(name)).iternext()) for name in DB_NAMES
        }
    shards = {p.name: p.read_bytes() for p in sorted((store.path / SHARDS_DIR).iterdir())}
    return {"stats": store.stats(), "lmdb": records, "shards": shards}


@pytest.fixture
def store(tmp_path, rng):
    """A writable map with two sequences (3 and 5 frames, 3 rows per shard: last shard open)."""
    with MapStore.create(tmp_path / "m", MapConfig(dim=DIM, store=StoreOptions(shard_rows=3))) as s:
        s.add_sequence(rng.standard_normal((3, DIM)), name="a")
        s.add_sequence(rng.standard_normal((5, DIM)), name="b")
        yield s


def _nan_at(rng, row, col, value):
    data = rng.standard_normal((4, DIM))
    data[row, col] = value
    return data


BAD_DESCRIPTORS = {
    "wrong-dim": (lambda rng: rng.standard_normal((4, DIM + 1)), DescriptorShapeError),
    "too-small-dim": (lambda rng: rng.standard_normal((4, DIM - 1)), DescriptorShapeError),
    "nan": (lambda rng: _nan_at(rng, 2, 1, np.nan), InvalidDescriptorError),
    "inf": (lambda rng: _nan_at(rng, 3, 0, np.inf), InvalidDescriptorError),
    "minus-inf": (lambda rng: _nan_at(rng, 0, 3, -np.inf), InvalidDescriptorError),
    "overflows-float32": (lambda rng: _nan_at(rng, 1, 1, 1e300), InvalidDescriptorError),
    "empty": (lambda rng: np.zeros((0, DIM)), EmptySequenceError),
    "1-d": (lambda rng: rng.standard_normal(DIM), DescriptorShapeError),
    "3-d": (lambda rng: rng.standard_normal((2, 2, DIM)), DescriptorShapeError),
    "scalar": (lambda rng: 1.0, DescriptorShapeError),
    "strings": (lambda rng: np.full((2, DIM), "x"), DescriptorShapeError),
    "objects": (lambda rng: np.array([[object()] * DIM]), DescriptorShapeError),
    "complex": (lambda rng: np.ones((2, DIM), dtype=complex), DescriptorShapeError),
    "bool": (lambda rng: np.ones((2, DIM), dtype=bool), DescriptorShapeError),
    "ragged": (lambda rng: np.array([[1.0, 2.0], [3.0]], dtype=object), DescriptorShapeError),
}


@pytest.mark.parametrize("make, error", BAD_DESCRIPTORS.values(), ids=BAD_DESCRIPTORS.keys())
def test_bad_descriptors_are_refused_and_nothing_is_committed(store, rng, make, error):
    before = snapshot(store)
    with pytest.raises(error):
        store.add_sequence(make(rng))
    assert snapshot(store) == before
    # The map is still usable, and the refused call consumed no id.
    assert store.add_sequence(rng.standard_normal((2, DIM))).sequence.seq_id == 2


BAD_CALLS = {
    "duplicate-name": (dict(name="b"), DuplicateNameError),
    "empty-name": (dict(name=""), InputError),
    "edge-to-unknown-sequence": (dict(edges=[EdgeSpec((None, 0), (7, 0))]), UnknownSequenceError),
    "edge-to-missing-image": (dict(edges=[EdgeSpec((None, 0), (1, 5))]), UnknownSequenceError),
    "edge-from-missing-image": (dict(edges=[EdgeSpec((0, 3), (None, 0))]), UnknownSequenceError),
    "edge-to-negative-image": (dict(edges=[EdgeSpec((None, 0), (1, -1))]), UnknownSequenceError),
    "edge-outside-new-sequence": (dict(edges=[EdgeSpec((None, 4), (0, 0))]), InputError),
    "edge-inside-new-sequence": (dict(edges=[EdgeSpec((None, 0), (None, 1))]), InputError),
    "edge-within-one-old-sequence": (dict(edges=[EdgeSpec((0, 0), (0, 1))]), InputError),
    "edge-weight-above-1": (dict(edges=[EdgeSpec((None, 0), (0, 0), weight=1.5)]), InputError),
    "edge-weight-nan": (dict(edges=[EdgeSpec((None, 0), (0, 0), weight=np.nan)]), InputError),
    # One bad edge among good ones refuses the whole sequence.
    "one-bad-edge-of-two": (
        dict(edges=[EdgeSpec((None, 0), (0, 0)), EdgeSpec((None, 1), (9, 0))]),
        UnknownSequenceError,
    ),
    "positions-wrong-rows": (dict(positions=np.zeros((3, 2))), InputError),
    "positions-one-column": (dict(positions=np.zeros((4, 1))), InputError),
    "positions-five-columns": (dict(positions=np.zeros((4, 5))), InputError),
    "positions-nan-x": (dict(positions=np.array([[np.nan, 0]] * 4)), InputError),
}


@pytest.mark.parametrize("kwargs, error", BAD_CALLS.values(), ids=BAD_CALLS.keys())
def test_bad_names_edges_and_positions_commit_nothing(store, rng, kwargs, error):
    before = snapshot(store)
    with pytest.raises(error):
        store.add_sequence(rng.standard_normal((4, DIM)), **kwargs)
    assert snapshot(store) == before


def test_a_failed_commit_truncates_the_shards_back(store, rng, monkeypatch):
    """An exception inside the LMDB transaction (after the rows were written) rolls back."""
    before = snapshot(store)

    def boom(*args, **kwargs):
        raise RuntimeError("injected")

    monkeypatch.setattr(store.uf, "add", boom)
    with pytest.raises(RuntimeError, match="injected"):
        store.add_sequence(rng.standard_normal((7, DIM)))  # would span into two new shards
    assert snapshot(store) == before


def test_readonly_map_refuses_writes(store, rng):
    path = store.path
    store.close()
    with MapStore.open(path, readonly=True) as ro:
        with pytest.raises(ReadOnlyMapError):
            ro.add_sequence(rng.standard_normal((2, DIM)))
        with pytest.raises(ReadOnlyMapError):
            ro.flush()


def test_unknown_sequences(store):
    with pytest.raises(UnknownSequenceError):
        store.sequence(2)
    with pytest.raises(UnknownSequenceError):
        store.sequence(-1)
    with pytest.raises(UnknownSequenceError):
        store.sequence_by_name("nope")
    with pytest.raises(UnknownSequenceError):
        store.component_of(5)


# --- create / open -------------------------------------------------------------------------


@pytest.mark.parametrize("content", ["file-inside", "subdir-inside", "path-is-a-file"])
def test_create_refuses_a_non_empty_path(tmp_path, content):
    target = tmp_path / "m"
    if content == "path-is-a-file":
        target.write_text("x")
    else:
        target.mkdir()
        (target / "x").mkdir() if content == "subdir-inside" else (target / "x").write_text("x")
    listing = sorted(p.name for p in tmp_path.rglob("*"))
    with pytest.raises(MapExistsError, match="non-empty"):
        MapStore.create(target, MapConfig(dim=2))
    assert sorted(p.name for p in tmp_path.rglob("*")) == listing


def test_create_refuses_an_existing_map(make_map):
    built = make_map((2,))
    with pytest.raises(MapExistsError):
        MapStore.create(built.path, built.config)


def test_create_accepts_an_empty_directory(tmp_path):
    (tmp_path / "m").mkdir()
    MapStore.create(tmp_path / "m", MapConfig(dim=2)).close()
    assert MapStore.open(tmp_path / "m", readonly=True).stats()["sequences"] == 0


def _foreign_lmdb(root: Path) -> None:
    env = lmdb.open(str(root / LMDB_DIR))
    with env.begin(write=True) as txn:
        txn.put(b"key", b"value")
    env.close()


NOT_MAPS = {
    "missing": lambda root: None,
    "empty-dir": lambda root: root.mkdir(),
    "a-file": lambda root: root.write_text("hello"),
    "dir-with-files": lambda root: (root.mkdir(), (root / "data.mdb").write_text("x")),
    "empty-lmdb-dir": lambda root: (root.mkdir(), (root / LMDB_DIR).mkdir()),
    "foreign-lmdb": lambda root: (root.mkdir(), (root / LMDB_DIR).mkdir(), _foreign_lmdb(root)),
}


@pytest.mark.parametrize("make", NOT_MAPS.values(), ids=NOT_MAPS.keys())
@pytest.mark.parametrize("readonly", [True, False], ids=["reader", "writer"])
def test_open_refuses_what_is_not_a_map(tmp_path, make, readonly):
    root = tmp_path / "m"
    make(root)
    with pytest.raises(NotAMapError):
        MapStore.open(root, readonly=readonly)


def test_open_does_not_modify_a_foreign_lmdb(tmp_path):
    root = tmp_path / "m"
    root.mkdir()
    (root / LMDB_DIR).mkdir()
    _foreign_lmdb(root)
    with pytest.raises(NotAMapError):
        MapStore.open(root)
    env = lmdb.open(str(root / LMDB_DIR), readonly=True, max_dbs=MAX_DBS)
    with env.begin() as txn:
        assert list(txn.cursor()) == [(b"key", b"value")]  # no named databases were added
    env.close()


def _set_meta(path: Path, key: bytes, value: bytes | None) -> None:
    env = lmdb.open(str(path / LMDB_DIR), max_dbs=MAX_DBS)
    meta = env.open_db(b"meta")
    with env.begin(write=True) as txn:
        if value is None:
            txn.delete(key, db=meta)
        else:
            txn.put(key, value, db=meta)
    env.close()


@pytest.mark.parametrize("readonly", [True, False], ids=["reader", "writer"])
def test_newer_schema_version_is_refused_with_a_clear_message(make_map, readonly):
    built = make_map((3,))
    newer = SCHEMA_VERSION + 1
    _set_meta(built.path, b"schema_version", str(newer).encode())
    with pytest.raises(SchemaVersionError) as info:
        MapStore.open(built.path, readonly=readonly)
    message = str(info.value)
    assert f"version {newer}" in message and f"version {SCHEMA_VERSION}" in message
    assert "upgrade sprint-map" in message
    # The refused open left nothing behind: no lock held, no LMDB environment left open in this
    # process (py-lmdb would refuse to open it again), the map itself untouched.
    _set_meta(built.path, b"schema_version", str(SCHEMA_VERSION).encode())
    with MapStore.open(built.path) as store:
        assert store.stats()["vertices"] == 3


def test_map_without_schema_version_is_not_a_map_and_open_leaks_nothing(make_map):
    built = make_map((3,))
    _set_meta(built.path, b"schema_version", None)
    with pytest.raises(NotAMapError):
        MapStore.open(built.path)
    _set_meta(built.path, b"schema_version", str(SCHEMA_VERSION).encode())
    MapStore.open(built.path).close()


# --- the writer lock -------------------------------------------------------------------------


def _worker(*args: str, **kwargs) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(WORKER), *args], text=True,
                            stdout=subprocess.PIPE, **kwargs)


def test_second_writer_in_the_same_process_is_refused(store):
    with pytest.raises(MapLockedError, match=str(store.path / LOCK_NAME)):
        MapStore.open(store.path)


def test_second_writer_in_another_process_is_refused_at_once(store):
    proc = _worker("try-open", str(store.path))
    out, _ = proc.communicate(timeout=60)
    result = json.loads(out)
    assert result["error"] == "MapLockedError"
    assert str(store.path / LOCK_NAME) in result["message"]
    assert f"pid {os.getpid()}" in result["message"]
    # Refused, not queued behind the lock (LMDB's own write lock would wait ~seconds).
    assert result["seconds"] < 1.0


def test_lock_dies_with_a_sigkilled_holder(make_map, rng):
    built = make_map((3,))
    holder = _worker("hold", str(built.path), stdin=subprocess.PIPE)
    try:
        assert holder.stdout is not None
        assert holder.stdout.readline().strip() == "locked"
        start = time.monotonic()
        with pytest.raises(MapLockedError, match=f"pid {holder.pid}"):
            MapStore.open(built.path)
        assert time.monotonic() - start < 1.0
        holder.send_signal(signal.SIGKILL)
        assert holder.wait(timeout=60) == -signal.SIGKILL
    finally:
        holder.kill()
        holder.wait()
    with MapStore.open(built.path) as store:  # no stale lock
        store.add_sequence(rng.standard_normal((2, built.config.dim)))
        assert store.stats()["sequences"] == 2


def test_readers_do_not_take_the_lock(store):
    """A reader in another process opens beside a writer (the writer here is this process)."""
    code = (
        "import sys, json; from sprint_map.storage.store import MapStore\n"
        "with MapStore.open(sys.argv[1], readonly=True) as m: print(json.dumps(m.stats()))"
    )
    out = subprocess.run([sys.executable, "-c", code, str(store.path)], capture_output=True,
                         text=True, timeout=60, check=True).stdout
    assert json.loads(out) == store.stats()


# --- I/O errors -----------------------------------------------------------------------------


def fail_nth(monkeypatch, name: str, n: int) -> list[int]:
    """Make the ``n``-th call of ``os.<name>`` fail with EIO; return the call counter."""
    original = getattr(os, name)
    calls = [0]

    def failing(*args, **kwargs):
        calls[0] += 1
        if calls[0] == n:
            raise OSError(errno.EIO, "Input/output error (injected)")
        return original(*args, **kwargs)

    monkeypatch.setattr(os, name, failing)
    return calls


# Adding 7 rows to a map whose last shard holds 2 of 3 rows writes 1 + 3 + 3 rows to three
# shard files (two of them new), fsyncs each, then fsyncs the directory (the 4th fsync).
IO_STEPS = [("pwrite", 1), ("pwrite", 3), ("fsync", 1), ("fsync", 2), ("fsync", 4),
            ("ftruncate", 2)]


@pytest.mark.parametrize("call, n", IO_STEPS, ids=[f"{c}-{n}" for c, n in IO_STEPS])
def test_io_error_while_writing_rows_fails_the_add_and_leaves_no_trace(
        store, rng, monkeypatch, call, n):
    before = snapshot(store)
    calls = fail_nth(monkeypatch, call, n)
    with pytest.raises(StorageIOError, match="injected"):
        store.add_sequence(rng.standard_normal((7, DIM)))
    assert calls[0] >= n  # the failure was really reached
    monkeypatch.undo()
    assert snapshot(store) == before
    assert store.add_sequence(rng.standard_normal((7, DIM))).sequence.seq_id == 2


@pytest.mark.parametrize("call", ["fsync", "replace"])
def test_io_error_while_persisting_the_index(store, rng, monkeypatch, call):
    store.search(rng.standard_normal((1, DIM)), k=1)
    fail_nth(monkeypatch, call, 1)
    with pytest.raises(StorageIOError, match="injected"):
        store.flush()
    monkeypatch.undo()
    index_dir = store.path / INDEX_DIR
    assert list(index_dir.iterdir()) == []  # no partial left, nothing published
    store.flush()  # a later persist succeeds
    assert [p.name for p in index_dir.iterdir()] == ["flat.000000000008.faiss"]


def test_index_writer_failure_is_a_storage_error(store, rng, monkeypatch):
    """FAISS reports a failed write (e.g. ENOSPC) as RuntimeError, after a partial file."""
    import faiss

    def torn_write(index, path):
        Path(path).write_bytes(b"torn")
        raise RuntimeError("Error in faiss::FileIOWriter: No space left on device")

    store.search(rng.standard_normal((1, DIM)), k=1)
    monkeypatch.setattr(faiss, "write_index", torn_write)
    with pytest.raises(StorageIOError, match="No space left"):
        store.flush()
    assert list((store.path / INDEX_DIR).iterdir()) == []
