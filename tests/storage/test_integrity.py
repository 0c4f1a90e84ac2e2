"""Storage integrity (issue 14): damage the map's files the way a disk, an operator or an attacker
would, and every command either works on the intact data or says the map is corrupt (exit 7).

Each test reproduces one finding of the issue on the code before the fix:

1. a shard that lost committed rows was refilled with zeros by the next ``ingest``, and
   ``check --repair`` rebuilt the index from the zeros;
3. an IVF segment overwritten in place passed ``check``; ``ingest`` committed, then died with a
   FAISS traceback, and the retry added the drive again;
4. a ``LOCK`` symlink made the writer truncate its target and write its pid into it;
8. a truncated ``data.mdb`` (or shard) killed every command with SIGBUS;
11. corrupt meta records gave ValueError/struct.error/JSONDecodeError tracebacks;
13. a failed ``init`` left ``LOCK`` and empty folders behind;
14. ``check`` compared only a sample of the exact index's rows.
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import subprocess
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import lmdb
import numpy as np
import pytest
from click.testing import CliRunner

from sprint_map.cli.main import main
from sprint_map.config import MapConfig, StoreOptions
from sprint_map.errors import DuplicateNameError, MapCorruptError
from sprint_map.storage.check import check_map
from sprint_map.storage.index import map_index as index_store
from sprint_map.storage.index.flat import file_bytes, index_files
from sprint_map.storage.index.manifest import MANIFEST
from sprint_map.storage.keys import EDGE_KEY, EDGE_VAL
from sprint_map.storage.lmdb_env import MAX_DBS
from sprint_map.storage.lock import writer_active
from sprint_map.storage.store import LMDB_DIR, MapStore

DIM = 16
CORRUPT = MapCorruptError.exit_code
SPRINT_MAP = shutil.which("sprint-map") or "sprint-map"


def cli(*args: Any) -> Any:
    return CliRunner().invoke(main, [str(a) for a in args])


def run(*args: Any, **kwargs: Any) -> subprocess.CompletedProcess[str]:
    """A real ``sprint-map`` process: a SIGBUS would be a negative return code, not a dead
    test runner."""
    return subprocess.run([SPRINT_MAP, *map(str, args)], capture_output=True, text=True,
                          timeout=120, **kwargs)


def one_error_line(stderr: str) -> str:
    lines = [line for line in stderr.splitlines() if not line.startswith("Warning: ")]
    assert len(lines) == 1 and lines[0].startswith("Error: "), stderr
    assert "Traceback" not in stderr
    return lines[0]


@contextmanager
def raw_lmdb(path: Path) -> Iterator[tuple[Any, Callable[[str], Any]]]:
    """A write transaction on the map's LMDB with the plain lmdb module (no sprint-map code)."""
    env = lmdb.open(str(path / LMDB_DIR), max_dbs=MAX_DBS)
    try:
        with env.begin(write=True) as txn:
            yield txn, lambda name: env.open_db(name.encode(), txn=txn, create=False)
    finally:
        env.close()


def drives(rng: np.random.Generator, n: int = 4, frames: int = 50) -> list[np.ndarray]:
    return [rng.standard_normal((frames, DIM)).astype(np.float32) for _ in range(n)]


@pytest.fixture
def npy(tmp_path: Path, rng: np.random.Generator) -> list[Path]:
    """Four drives as ``.npy`` files."""
    out = []
    for i, rows in enumerate(drives(rng)):
        out.append(tmp_path / f"d{i}.npy")
        np.save(out[-1], rows)
    return out


def build(path: Path, files: list[Path], config: MapConfig | None = None) -> Path:
    """A map of the first three drives (each under its file's name), closed."""
    with MapStore.create(path, config or MapConfig(dim=DIM, store=StoreOptions(shard_rows=64))) as store:
        for file in files[:3]:
            store.add_sequence(np.load(file), name=file.stem)
        store.search(np.load(files[0])[:1], k=1)  # the flat index is persisted at close
    return path


def descriptors_of(path: Path) -> list[np.ndarray]:
    with MapStore.open(path, readonly=True) as store:
        return [np.array(store.descriptors(s.seq_id)) for s in store.sequences()]


# --- 1: shards that lost committed rows ---------------------------------------------------------


@pytest.mark.parametrize("damage", ["truncate-open", "delete-open", "truncate-sealed",
                                    "delete-sealed"])
def test_a_shard_that_lost_rows_is_never_refilled(tmp_path, npy, damage):
    """150 rows in shards of 64: shard 2 is the open one, 0 and 1 are sealed."""
    path = build(tmp_path / "m", npy)
    shard = path / "shards" / ("shard-000002.f32" if "open" in damage else "shard-000000.f32")
    if damage.startswith("truncate"):
        os.truncate(shard, shard.stat().st_size - 1000)
    else:
        shard.unlink()
    size = shard.stat().st_size if shard.exists() else None
    assert cli("check", path).exit_code == 1
    result = cli("ingest", path, npy[3])
    assert result.exit_code == CORRUPT, result.output
    assert "committed descriptors are lost" in one_error_line(result.output)
    repaired = cli("check", path, "--repair", "--json")
    assert repaired.exit_code == 1
    report = json.loads(repaired.output)
    assert report["repaired"] == [] and "nothing touched" in report["skipped"][0]
    assert any(shard.name in v for v in report["unrepaired"])
    # Nothing invented: the shard is as damaged as before, the map still has 3 drives.
    assert (shard.stat().st_size if shard.exists() else None) == size
    assert cli("check", path).exit_code == 1
    with MapStore.open(path, readonly=True) as store:
        assert store.stats()["sequences"] == 3
        with pytest.raises(MapCorruptError):
            store.descriptors(2 if "open" in damage else 0)


def test_a_zero_filled_shard_row_is_caught_by_its_digest(tmp_path, npy):
    """Rows changed in place (the size intact) are caught by the sequence's content digest."""
    path = build(tmp_path / "m", npy)
    shard = path / "shards" / "shard-000001.f32"
    with shard.open("r+b") as fh:
        fh.seek(10 * DIM * 4)
        fh.write(bytes(DIM * 4))
    report = json.loads(cli("check", path, "--json").output)
    assert not report["ok"]
    assert any("differ from the digest committed with them" in v for v in report["violations"])


# --- 3: segments changed in place, work after the commit, retries --------------------------------

SEGMENTED = MapConfig(dim=DIM, store=StoreOptions(index_type="ivf-sq8", index_segment_rows=128, index_nlist=4, index_nprobe=2, index_merge_factor=4))


@pytest.fixture
def segmented(tmp_path: Path, rng: np.random.Generator) -> tuple[Path, list[Path]]:
    files = []
    for i in range(4):
        files.append(tmp_path / f"s{i}.npy")
        np.save(files[-1], rng.standard_normal((200, DIM)).astype(np.float32))
    return build(tmp_path / "seg", files, SEGMENTED), files


def segment_file(path: Path) -> Path:
    manifest = json.loads((path / "index" / MANIFEST).read_text())
    return path / "index" / manifest["segments"][0]["file"]


@pytest.mark.parametrize("offset", [0, 600, 6000])
def test_a_segment_overwritten_in_place_is_caught_and_rebuilt(segmented, offset):
    path, files = segmented
    before = descriptors_of(path)
    seg = segment_file(path)
    data = bytearray(seg.read_bytes())
    data[offset : offset + 400] = bytes(b ^ 0x5A for b in data[offset : offset + 400])
    seg.write_bytes(bytes(data))
    report = json.loads(cli("check", path, "--json").output)
    assert any("fails its checksum" in v for v in report["violations"]), report
    assert report["checked"]["index_files_checksummed"] >= 1
    located = run("localize", path, files[3], "--quiet", "--json")
    assert located.returncode == 0, located.stderr
    ingested = run("ingest", path, files[3], "--quiet")
    assert ingested.returncode == 0 and "Traceback" not in ingested.stderr, ingested.stderr
    retry = run("ingest", path, files[3], "--quiet")
    assert retry.returncode == 0 and "already committed" in retry.stderr, retry.stderr
    with MapStore.open(path, readonly=True) as store:
        assert store.stats()["sequences"] == 4  # added once
        assert check_map(store).ok
    assert all(np.array_equal(a, b) for a, b in zip(before, descriptors_of(path)[:3],
                                                    strict=True))


def test_a_manifest_without_checksums_still_reads(segmented):
    """Maps written before segment checksums: the files are trusted on their sizes."""
    path, files = segmented
    manifest = json.loads((path / "index" / MANIFEST).read_text())
    for key in ("model_checksum", "pca_checksum"):
        manifest.pop(key)
    for seg in manifest["segments"]:
        seg.pop("checksum")
    (path / "index" / MANIFEST).write_text(json.dumps(manifest))
    with MapStore.open(path, readonly=True) as store:
        assert check_map(store).ok
        rows = np.load(files[0])
        _, ids = store.search(rows, k=1)
        assert np.array_equal(ids[:, 0], np.arange(len(rows)))


def test_a_failure_after_the_commit_is_a_warning(tmp_path, npy, monkeypatch):
    path = build(tmp_path / "m", npy)

    def broken(*args: Any, **kwargs: Any) -> bool:
        raise RuntimeError("Error in faiss::read_index: garbled")

    monkeypatch.setattr(index_store.IndexStore, "after_commit", broken)
    with MapStore.open(path) as store:
        added = store.add_sequence(np.load(npy[3]), name="d3")
        assert not added.already_committed and added.sequence.seq_id == 3
        assert any("committed, but the index cache was not updated" in w
                   for w in store.warnings)
        again = store.add_sequence(np.load(npy[3]), name="d3")  # the retry
        assert again.already_committed and again.sequence == added.sequence
        assert store.stats()["sequences"] == 4


def test_a_retry_is_reported_not_added(tmp_path, npy):
    path = build(tmp_path / "m", npy)
    first = cli("ingest", path, npy[3], "--quiet")
    assert first.exit_code == 0, first.output
    with MapStore.open(path, readonly=True) as store:
        state = (store.stats(), [np.array(d) for d in descriptors_of_store(store)])
        size = (path / "shards" / "shard-000003.f32").stat().st_size
    again = cli("ingest", path, npy[3], "--quiet")
    assert again.exit_code == 0 and "already committed" in again.output, again.output
    assert "sequence 3 (d3) was already committed with these 50 frames: nothing added" in (
        again.output)
    retried = json.loads(cli("ingest", path, npy[3], "--quiet", "--json").stdout)
    assert retried["already_committed"] and retried["seq_id"] == 3
    with MapStore.open(path, readonly=True) as store:
        assert store.stats() == state[0]
    assert (path / "shards" / "shard-000003.f32").stat().st_size == size
    other = np.load(npy[3]) + 1
    np.save(path.parent / "other.npy", other)
    refused = cli("ingest", path, path.parent / "other.npy", "--name", "d3")
    assert refused.exit_code == DuplicateNameError.exit_code
    assert "already exists with other descriptors" in refused.output
    assert (path / "shards" / "shard-000003.f32").stat().st_size == size  # nothing written


def descriptors_of_store(store: MapStore) -> list[np.ndarray]:
    return [store.descriptors(s.seq_id) for s in store.sequences()]


def test_a_map_without_digests_opens_and_refuses_a_name_at_once(tmp_path, npy):
    """A map written before digests (no ``digests`` database): read, checked, written; its
    names are refused before any row is written, as they always were."""
    path = build(tmp_path / "m", npy)
    with raw_lmdb(path) as (txn, db):
        txn.drop(db("digests"), delete=True)
    with MapStore.open(path, readonly=True) as store:
        assert not store.env.has_db("digests")
        report = check_map(store)
        assert report.ok and report.checked["digests_missing"] == 3
    with MapStore.open(path) as store, pytest.raises(DuplicateNameError):
        store.begin_sequence("d0")
    with MapStore.open(path) as store:
        store.add_sequence(np.load(npy[3]), name="d3")
    with MapStore.open(path, readonly=True) as store:
        report = check_map(store)
        assert report.ok and report.checked["sequence_digests_verified"] == 1


# --- 4: the lock file --------------------------------------------------------------------------


@pytest.mark.parametrize("link", ["symlink", "hardlink"])
def test_the_writer_never_writes_through_a_linked_lock_file(tmp_path, npy, link):
    path = build(tmp_path / "m", npy)
    outside = tmp_path / "precious.txt"
    outside.write_text("precious\n")
    (path / "LOCK").unlink()
    if link == "symlink":
        (path / "LOCK").symlink_to(outside)
    else:
        os.link(outside, path / "LOCK")
    result = cli("ingest", path, npy[3])
    assert result.exit_code == CORRUPT
    assert "LOCK" in one_error_line(result.output)
    assert outside.read_text() == "precious\n"
    assert not writer_active(path)
    assert cli("info", path).exit_code == 0  # readers do not need the lock


# --- 8: files shorter than LMDB or the shards say ------------------------------------------------


@pytest.mark.parametrize("command", ["info", "check", "localize", "ingest"])
def test_a_truncated_data_mdb_is_the_corrupt_map_error_not_sigbus(tmp_path, npy, command):
    path = build(tmp_path / "m", npy)
    data = path / LMDB_DIR / "data.mdb"
    os.truncate(data, data.stat().st_size // 2)
    args = [command, path] + ([npy[3], "--quiet"] if command in ("localize", "ingest") else [])
    result = run(*args)
    assert result.returncode == CORRUPT, (result.returncode, result.stderr)
    assert "data.mdb is truncated" in one_error_line(result.stderr)


def test_a_reader_never_maps_a_truncated_shard(tmp_path, npy):
    path = build(tmp_path / "m", npy)
    for index in index_files(path / "index"):
        index[1].unlink()  # the search must read the shards
    shard = path / "shards" / "shard-000000.f32"
    os.truncate(shard, 100)
    result = run("localize", path, npy[3], "--quiet")
    assert result.returncode == CORRUPT, (result.returncode, result.stderr)
    assert "shard-000000.f32" in one_error_line(result.stderr)


# --- 11: corrupt meta and sequence records -------------------------------------------------------

RECORDS = {
    "schema_version": ("meta", b"schema_version", b"abc"),
    "next_vertex_id": ("meta", b"next_vertex_id", b"garbage"),
    "created": ("meta", b"created", b"yesterday"),
    "config-json": ("meta", b"config", b"{broken"),
    "config-list": ("meta", b"config", b"[1, 2]"),
    "config-bytes": ("meta", b"config", b"\xff\xfe"),
    "sequence": ("sequences", b"\x00\x00\x00\x01", b'{"seq_id": "x"}'),
    "sequence-json": ("sequences", b"\x00\x00\x00\x01", b"\x00garbage"),
    "name": ("seq_names", b"\xff\xfe", b"\x00\x00\x00\x01"),
    "uf": ("uf", b"\x00\x00\x00\x01", b"\x01"),
}


@pytest.mark.parametrize("record", RECORDS)
@pytest.mark.parametrize("command", [["info"], ["check"], ["check", "--repair"]])
def test_a_corrupt_record_is_the_corrupt_map_error(tmp_path, npy, record, command):
    path = build(tmp_path / "m", npy)
    db, key, value = RECORDS[record]
    with raw_lmdb(path) as (txn, dbs):
        txn.put(key, value, db=dbs(db))
    result = cli(*command, path)
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    if result.exit_code == 0:  # info reads only the meta and counters
        assert command == ["info"] and db != "meta"
        return
    if command == ["check"] and result.exit_code == 1:  # found as a violation: also fine
        return
    assert result.exit_code == CORRUPT, result.output
    assert "corrupt" in one_error_line(result.output)


def test_an_edge_record_leaving_its_component_is_the_corrupt_map_error(tmp_path, npy):
    """A garbled edge key (a bit flipped in LMDB: no checksum there) that points into another
    component: localize said ValueError 'an edge end is not a vertex of this component'."""
    path = build(tmp_path / "m", npy)  # no edges: every drive is its own component
    with raw_lmdb(path) as (txn, db):
        txn.put(EDGE_KEY.pack(3, 120), EDGE_VAL.pack(1.0, 0, 0, 0.0), db=db("edges"))
    result = cli("localize", path, npy[0], "--quiet")
    assert result.exit_code == CORRUPT, result.output
    assert "edge 3 -> 120 of component 0 leaves it" in one_error_line(result.output)
    assert cli("check", path).exit_code == 1  # the check names it too


# --- 13: a failed init leaves nothing ------------------------------------------------------------


@pytest.mark.parametrize("where", ["absent", "nested", "empty-dir"])
def test_a_failed_init_removes_what_it_created(tmp_path, where):
    path = tmp_path / ("a/b/map" if where == "nested" else "map")
    if where == "empty-dir":
        path.mkdir()
    config = tmp_path / "huge.json"
    config.write_text(json.dumps({"initial_map_size": 2**62}))
    result = cli("init", path, "--dim", DIM, "--config", config)
    assert result.exit_code != 0 and result.exception is None or isinstance(
        result.exception, SystemExit), result.output
    if where == "empty-dir":
        assert path.is_dir() and not any(path.iterdir())
    else:
        assert not (tmp_path / "a").exists() and not path.exists()
    assert cli("init", path, "--dim", DIM).exit_code == 0
    assert cli("info", path).exit_code == 0


def test_a_full_disk_at_init_leaves_nothing(tmp_path):
    path = tmp_path / "map"

    def small_files() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))

    result = run("init", path, "--dim", DIM, preexec_fn=small_files)
    assert result.returncode != 0 and "Traceback" not in result.stderr, result.stderr
    assert not path.exists(), sorted(p.name for p in path.rglob("*"))
    assert run("init", path, "--dim", DIM).returncode == 0


# --- 14: check compares every row of the exact index ---------------------------------------------


def test_check_compares_every_vector_of_the_exact_index(tmp_path, rng):
    total = 3000
    with MapStore.create(tmp_path / "m", MapConfig(dim=8)) as store:
        store.add_sequence(rng.standard_normal((total, 8)).astype(np.float32), name="big")
        store.search(np.zeros((1, 8), np.float32), k=1)
    path = tmp_path / "m"
    with MapStore.open(path, readonly=True) as store:
        report = check_map(store)
        assert report.ok and report.checked["index_vectors_compared"] == total
    # A vertex the old sample (vertex 0, the last and 32 seeded draws) never looked at.
    sampled = set(np.random.default_rng(0).integers(0, total, 32).tolist()) | {0, total - 1}
    victim = next(v for v in range(1234, total) if v not in sampled)
    (_, index_file), = index_files(path / "index")
    header = file_bytes(8, 0)
    with index_file.open("r+b") as fh:
        fh.seek(header + victim * 8 * 4 + 4)  # the vectors come first, then the ids
        fh.write(b"\x00\x00\x80\x7f")
    with MapStore.open(path, readonly=True) as store:
        report = check_map(store)
    assert f"index vector of vertex {victim} differs from its shard row" in report.violations

