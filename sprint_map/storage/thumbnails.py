"""Per-frame thumbnails kept in the map: small JPEG images for viewers, as opaque bytes.

A drive ingested with ``--thumbnails`` stores one small JPEG per frame in the ``thumbnails``
LMDB database, keyed by ``(seq_id, image_id)`` (:data:`~sprint_map.storage.keys.THUMB_KEY`,
big-endian, so a sequence's thumbnails are one key range). They are written in the very
transaction that commits the sequence (the commit point: a drive has all its thumbnails or
none), deleted in the transaction that removes it, copied as they are by ``compact`` (sequence
ids are kept) whose compacted LMDB copy reclaims their pages, and verified by ``check``.

The storage layer knows them only as bytes: it checks the JPEG signature (start-of-image
``FF D8`` at the start, end-of-image ``FF D9`` at the end) and a size bound, never decodes
them; making them from images is the front end's job (:mod:`sprint_map.frontend.thumbnails`).

Invariants (``check``'s ``thumbnails`` area): every key is 8 bytes and names a frame of a live
sequence; every value carries the JPEG signature; a sequence has a thumbnail for every frame or
for none. They are not derivable from anything else in the map (the images are not kept), so
``check --repair`` can only drop what breaks them (:func:`drop_broken`), and says so.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import lmdb

from sprint_map.errors import InputError, MapCorruptError
from sprint_map.storage.keys import THUMB_KEY, sequence_keys
from sprint_map.storage.lmdb_env import LmdbEnv

THUMBNAILS_DB = "thumbnails"
JPEG_START = b"\xff\xd8"
JPEG_END = b"\xff\xd9"
#: Largest thumbnail accepted: a thumbnail is small (the front end's are about 2 KiB); this only
#: stops a caller from filling the map with full-size images by mistake.
MAX_THUMBNAIL_BYTES = 256 * 1024


def is_jpeg(data: bytes | memoryview) -> bool:
    """Whether ``data`` carries the JPEG signature (SOI first, EOI last). O(1)."""
    return len(data) >= 4 and bytes(data[:2]) == JPEG_START and bytes(data[-2:]) == JPEG_END


def validate_thumbnails(thumbnails: Sequence[bytes], frames: int) -> list[bytes]:
    """The thumbnails of a ``frames``-frame sequence, checked: one per frame, JPEG bytes.

    Raises
    ------
    InputError
        Not one per frame, or one that is not JPEG bytes or is larger than
        :data:`MAX_THUMBNAIL_BYTES` (nothing is written).
    """
    out = list(thumbnails)
    if len(out) != frames:
        raise InputError(f"{len(out)} thumbnails for a sequence of {frames} frames "
                         "(one per frame, or none)")
    for i, data in enumerate(out):
        if not isinstance(data, bytes | bytearray) or not is_jpeg(data):
            raise InputError(f"thumbnail of frame {i} is not JPEG bytes")
        if len(data) > MAX_THUMBNAIL_BYTES:
            raise InputError(f"thumbnail of frame {i} has {len(data)} bytes (at most "
                             f"{MAX_THUMBNAIL_BYTES}: thumbnails are small images)")
    return [bytes(d) for d in out]


def put_thumbnails(txn: lmdb.Transaction, env: LmdbEnv, seq_id: int,
                   thumbnails: Sequence[bytes]) -> None:
    """Write a new sequence's thumbnails (validated) in ``txn``. O(frames) puts."""
    txn.cursor(db=env.db(THUMBNAILS_DB)).putmulti(
        (THUMB_KEY.pack(seq_id, i), data) for i, data in enumerate(thumbnails))


def get_thumbnail(txn: lmdb.Transaction, env: LmdbEnv, seq_id: int, image_id: int
                  ) -> bytes | None:
    """The thumbnail of frame ``image_id`` of sequence ``seq_id``, or None. O(log n)."""
    if not env.has_db(THUMBNAILS_DB):  # a map written before thumbnails, opened read-only
        return None
    raw = txn.get(THUMB_KEY.pack(seq_id, image_id), db=env.db(THUMBNAILS_DB))
    return None if raw is None else bytes(raw)


def _seq_keys(txn: lmdb.Transaction, env: LmdbEnv, seq_id: int) -> list[bytes]:
    """Keys of sequence ``seq_id``'s thumbnails: one seek and a range scan."""
    if not env.has_db(THUMBNAILS_DB):
        return []
    return sequence_keys(txn, env.db(THUMBNAILS_DB), seq_id)


def count_thumbnails(txn: lmdb.Transaction, env: LmdbEnv, seq_id: int) -> int:
    """Thumbnails sequence ``seq_id`` has (its length or 0 in a sound map). O(log n + count)."""
    return len(_seq_keys(txn, env, seq_id))


def delete_thumbnails(txn: lmdb.Transaction, env: LmdbEnv, seq_id: int) -> int:
    """Delete sequence ``seq_id``'s thumbnails in ``txn``; return how many. O(log n + count)."""
    keys = _seq_keys(txn, env, seq_id)
    for key in keys:
        txn.delete(key, db=env.db(THUMBNAILS_DB))
    return len(keys)


@dataclass
class ThumbnailScan:
    """What :func:`scan_thumbnails` found: counts and the records that break the invariants."""

    #: thumbnails per live sequence that has any
    counts: dict[int, int] = field(default_factory=dict)
    #: bytes of all thumbnail values
    total_bytes: int = 0
    #: one message per problem
    problems: list[str] = field(default_factory=list)
    #: keys that name no frame of a live sequence (or are not keys of this database)
    stray_keys: list[bytes] = field(default_factory=list)
    #: live sequences whose thumbnails are broken: incomplete, or one is not JPEG bytes
    broken_seqs: set[int] = field(default_factory=set)


#: A caller's test that a thumbnail is an image (the front end decodes it; storage cannot).
ThumbnailTest = Callable[[bytes], bool]


def scan_thumbnails(txn: lmdb.Transaction, env: LmdbEnv, lengths: dict[int, int],
                    decodes: ThumbnailTest | None = None) -> ThumbnailScan:
    """Check every thumbnail against the live sequences ``lengths`` (seq_id -> frames): the
    signature, :data:`MAX_THUMBNAIL_BYTES`, and ``decodes(value)`` when given.

    Notes
    -----
    One cursor pass: O(thumbnails) reads of O(thumbnail bytes) in all, O(sequences) memory.
    """
    scan = ThumbnailScan()
    if not env.has_db(THUMBNAILS_DB):
        return scan
    for key, value in txn.cursor(db=env.db(THUMBNAILS_DB)):
        try:
            seq_id, image_id = THUMB_KEY.unpack(key)
        except MapCorruptError:
            scan.stray_keys.append(bytes(key))
            scan.problems.append(f"thumbnail key {bytes(key).hex()} is not a (sequence, "
                                 "image) key")
            continue
        length = lengths.get(seq_id)
        if length is None or image_id >= length:
            scan.stray_keys.append(bytes(key))
            where = "no sequence" if length is None else f"{length} frames"
            scan.problems.append(f"thumbnail of sequence {seq_id} image {image_id} names no "
                                 f"frame of the map ({where})")
            continue
        scan.counts[seq_id] = scan.counts.get(seq_id, 0) + 1
        scan.total_bytes += len(value)
        if seq_id in scan.broken_seqs:
            continue
        if not is_jpeg(value) or len(value) > MAX_THUMBNAIL_BYTES:
            scan.broken_seqs.add(seq_id)
            scan.problems.append(f"thumbnail of sequence {seq_id} image {image_id} is not "
                                 f"JPEG bytes of a thumbnail ({len(value)} bytes)")
        elif decodes is not None and not decodes(bytes(value)):
            scan.broken_seqs.add(seq_id)
            scan.problems.append(f"thumbnail of sequence {seq_id} image {image_id} does not "
                                 f"decode as an image ({len(value)} bytes)")
    for seq_id, count in sorted(scan.counts.items()):
        if count != lengths[seq_id] and seq_id not in scan.broken_seqs:
            scan.broken_seqs.add(seq_id)
            scan.problems.append(f"sequence {seq_id} has {count} thumbnails for "
                                 f"{lengths[seq_id]} frames (one per frame, or none)")
    return scan


def drop_broken(txn: lmdb.Transaction, env: LmdbEnv, lengths: dict[int, int],
                decodes: ThumbnailTest | None = None) -> list[str]:
    """Delete, in ``txn``, the thumbnails that break the invariants: stray keys, and every
    thumbnail of a sequence whose set is broken (the images are not kept, so nothing can be
    rebuilt; a sequence keeps all its thumbnails or none). Returns what was done.

    Notes
    -----
    O(thumbnails) reads (:func:`scan_thumbnails`) plus the deletes.
    """
    scan = scan_thumbnails(txn, env, lengths, decodes)
    actions = []
    for key in scan.stray_keys:
        txn.delete(key, db=env.db(THUMBNAILS_DB))
    if scan.stray_keys:
        actions.append(f"dropped {len(scan.stray_keys)} thumbnails that name no frame of the map")
    for seq_id in sorted(scan.broken_seqs):
        dropped = delete_thumbnails(txn, env, seq_id)
        actions.append(f"dropped the {dropped} thumbnails of sequence {seq_id} (incomplete or "
                       "not JPEG; they cannot be rebuilt from the map: re-ingest the drive "
                       "with --thumbnails to make them again)")
    return actions


__all__ = [
    "JPEG_END",
    "JPEG_START",
    "MAX_THUMBNAIL_BYTES",
    "THUMBNAILS_DB",
    "ThumbnailScan",
    "ThumbnailTest",
    "count_thumbnails",
    "delete_thumbnails",
    "drop_broken",
    "get_thumbnail",
    "is_jpeg",
    "put_thumbnails",
    "scan_thumbnails",
    "validate_thumbnails",
]
