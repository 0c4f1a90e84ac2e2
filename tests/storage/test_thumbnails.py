"""Thumbnails in the map's LMDB: committed with their drive, removed, compacted, checked."""

from __future__ import annotations

import numpy as np
import pytest

from sprint_map.config import MapConfig, StoreOptions
from sprint_map.errors import InputError, UnknownSequenceError
from sprint_map.storage.check import check_map
from sprint_map.storage.keys import THUMB_KEY
from sprint_map.storage.repair import repair_map
from sprint_map.storage.store import MapStore
from sprint_map.storage.thumbnails import MAX_THUMBNAIL_BYTES, THUMBNAILS_DB, is_jpeg


def fake_jpegs(rng: np.random.Generator, n: int) -> list[bytes]:
    """Bytes with the JPEG signature and random content (storage never decodes them)."""
    return [b"\xff\xd8\xff\xe0" + rng.bytes(int(rng.integers(10, 300))) + b"\xff\xd9"
            for _ in range(n)]


@pytest.fixture
def store_with_thumbs(tmp_path, rng):
    """Sequences 0 (no thumbnails), 1 and 2 (thumbnails), 3 (none); returns (path, thumbs)."""
    path = tmp_path / "t.map"
    thumbs: dict[int, list[bytes]] = {}
    with MapStore.create(path, MapConfig(dim=8, store=StoreOptions(shard_rows=32))) as store:
        for seq, n in enumerate((12, 20, 7, 9)):
            rows = rng.standard_normal((n, 8)).astype(np.float32)
            if seq in (1, 2):
                thumbs[seq] = fake_jpegs(rng, n)
                store.add_sequence(rows, name=f"s{seq}", thumbnails=thumbs[seq])
            else:
                store.add_sequence(rows, name=f"s{seq}")
    return path, thumbs


def all_thumbnails(store: MapStore) -> dict[tuple[int, int], bytes]:
    out = {}
    for rec in store.sequences():
        for image in range(rec.length):
            data = store.thumbnail(rec.seq_id, image)
            if data is not None:
                out[(rec.seq_id, image)] = data
    return out


def test_thumbnails_read_back_per_frame(store_with_thumbs):
    path, thumbs = store_with_thumbs
    with MapStore.open(path, readonly=True) as store:
        got = all_thumbnails(store)
        assert got == {(s, i): d for s, ds in thumbs.items() for i, d in enumerate(ds)}
        assert [store.thumbnail_count(s) for s in range(4)] == [0, 20, 7, 0]
        with pytest.raises(UnknownSequenceError):
            store.thumbnail(1, 20)  # no such frame
        with pytest.raises(UnknownSequenceError):
            store.thumbnail(9, 0)
        assert check_map(store).checked["thumbnails"] == 27
        assert check_map(store).ok


@pytest.mark.parametrize("bad", ["count", "not-jpeg", "too-big", "str"])
def test_bad_thumbnails_commit_nothing(tmp_path, rng, bad):
    path = tmp_path / "b.map"
    rows = rng.standard_normal((5, 8)).astype(np.float32)
    thumbs: list = fake_jpegs(rng, 5)
    if bad == "count":
        thumbs = thumbs[:4]
    elif bad == "not-jpeg":
        thumbs[2] = b"\x89PNG\r\n" + thumbs[2]
    elif bad == "too-big":
        thumbs[3] = b"\xff\xd8" + bytes(MAX_THUMBNAIL_BYTES) + b"\xff\xd9"
    else:
        thumbs[0] = "\xff\xd8 text \xff\xd9"
    with MapStore.create(path, MapConfig(dim=8)) as store:
        with pytest.raises(InputError):
            store.add_sequence(rows, name="x", thumbnails=thumbs)
        assert store.stats()["sequences"] == 0
        with store.env.read() as txn:
            assert txn.stat(store.env.db(THUMBNAILS_DB))["entries"] == 0
        assert check_map(store).ok


def test_streamed_commit_reads_thumbnails_at_the_commit(tmp_path, rng):
    """A list filled while the rows stream (as a frame source fills it) is read at commit."""
    rows = rng.standard_normal((40, 8)).astype(np.float32)
    thumbs = fake_jpegs(rng, 40)
    sink: list[bytes] = []
    with MapStore.create(tmp_path / "s.map", MapConfig(dim=8)) as store:
        with store.begin_sequence("streamed") as writer:
            for start in range(0, 40, 16):
                writer.append(rows[start:start + 16])
                sink.extend(thumbs[start:start + 16])
            writer.commit(thumbnails=sink)
        assert [store.thumbnail(0, i) for i in range(40)] == thumbs


def test_remove_deletes_and_compact_reclaims_them(store_with_thumbs):
    path, thumbs = store_with_thumbs
    with MapStore.open(path) as store:
        store.remove_sequences([1])
        with store.env.read() as txn:
            assert txn.stat(store.env.db(THUMBNAILS_DB))["entries"] == 7
        assert check_map(store).ok
        before = store.env.env.info()["last_pgno"]
        report = store.compact()
        assert report.sequences == 3
        assert store.env.env.info()["last_pgno"] < before
        assert all_thumbnails(store) == {(2, i): d for i, d in enumerate(thumbs[2])}
    with MapStore.open(path, readonly=True) as store:
        assert check_map(store).ok


def corrupt(path, how: str) -> None:
    with MapStore.open(path) as store:
        db = store.env.db(THUMBNAILS_DB)

        def body(txn):
            if how == "missing":
                txn.delete(THUMB_KEY.pack(1, 5), db=db)
            elif how == "garbled":
                txn.put(THUMB_KEY.pack(2, 3), b"not a jpeg", db=db)
            elif how == "stray":
                txn.put(THUMB_KEY.pack(2, 7), b"\xff\xd8xx\xff\xd9", db=db)  # s2 has 7 frames
                txn.put(THUMB_KEY.pack(8, 0), b"\xff\xd8xx\xff\xd9", db=db)  # no sequence 8
            else:
                txn.put(b"\x00\x01", b"\xff\xd8xx\xff\xd9", db=db)  # not a key of this db

        store.env.write(body)


@pytest.mark.parametrize("how", ["missing", "garbled", "stray", "badkey"])
def test_check_finds_and_repair_drops_broken_thumbnails(store_with_thumbs, how):
    path, thumbs = store_with_thumbs
    corrupt(path, how)
    with MapStore.open(path, readonly=True) as store:
        report = check_map(store)
    assert report.areas == {"thumbnails"}, report.violations
    fixed = repair_map(path)
    assert fixed.ok, fixed.after.violations
    assert any("dropped" in r for r in fixed.repaired), fixed.repaired
    with MapStore.open(path, readonly=True) as store:
        kept = all_thumbnails(store)
    expected = {(s, i): d for s, ds in thumbs.items() for i, d in enumerate(ds)}
    if how == "missing":  # sequence 1 keeps none: all of a drive's thumbnails, or none
        expected = {k: v for k, v in expected.items() if k[0] != 1}
        assert any("cannot be rebuilt" in r for r in fixed.repaired)
    elif how == "garbled":
        expected = {k: v for k, v in expected.items() if k[0] != 2}
    assert kept == expected


def test_is_jpeg_signature():
    assert is_jpeg(b"\xff\xd8ab\xff\xd9")
    assert not is_jpeg(b"\xff\xd8\xff\xd9"[:3])
    assert not is_jpeg(b"\xff\xd8abc")
