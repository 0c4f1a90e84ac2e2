"""Per-drive statistics kept in the map: each drive's frame count and mean descriptor.

A drive's statistics describe its condition (the shared component of its descriptors: season,
light, camera); the upper layers decide what they mean (:mod:`sprint_map.frontend.centring`).
The storage layer knows them as a count and a float32 vector of the map's dimension, in the
``drive_stats`` LMDB database keyed by ``>I seq_id``: ``>Q`` frames, then ``dim`` little-endian
float32. They are written in the transaction that commits the sequence (the commit point),
deleted in the one that removes it, copied as they are by ``compact`` and ``summarize`` (a
summary keeps the statistics of the drive as it was driven), untouched by ``unmerge``.

Invariants (``check``'s ``drive_stats`` area): every key is 4 bytes and names a live sequence;
every value is ``8 + 4 * dim`` bytes, its mean finite, its count at least 1. A sequence without
a record was written before statistics existed (or by ``add_sequence`` of a caller that gave
none). They are not derivable once the drive's original descriptors are gone, so ``check
--repair`` can only drop a record that breaks them (:func:`drop_broken_stats`), and says so.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable

import lmdb
import numpy as np

from sprint_map.errors import InputError, MapCorruptError
from sprint_map.storage.keys import u32
from sprint_map.storage.lmdb_env import LmdbEnv

__all__ = ["DRIVE_STATS_DB", "check_drive_stats", "decode_drive_stats", "delete_drive_stats",
           "drop_broken_stats", "encode_drive_stats", "get_drive_stats", "put_drive_stats"]

DRIVE_STATS_DB = "drive_stats"
_COUNT = struct.Struct(">Q")


def encode_drive_stats(frames: int, mean: np.ndarray, dim: int) -> bytes:
    """The record of a drive's ``frames`` and ``mean`` (``dim`` finite values); InputError
    otherwise. O(dim)."""
    vec = np.asarray(mean, dtype=np.float64).reshape(-1)
    if vec.shape != (dim,):
        raise InputError(f"drive statistics of dimension {vec.size}, the map has {dim}")
    if not (isinstance(frames, int | np.integer) and frames >= 1):
        raise InputError(f"drive statistics need a positive frame count, got {frames!r}")
    if not np.isfinite(vec).all():
        raise InputError("drive statistics contain NaN or Inf")
    return _COUNT.pack(int(frames)) + vec.astype("<f4").tobytes()


def decode_drive_stats(raw: bytes | memoryview, dim: int, what: str = "drive statistics"
                       ) -> tuple[int, np.ndarray]:
    """``(frames, mean)`` of a record; MapCorruptError if it is not one. O(dim)."""
    data = bytes(raw)
    if len(data) != _COUNT.size + 4 * dim:
        raise MapCorruptError(f"{what}: {len(data)} bytes, not {_COUNT.size + 4 * dim}")
    (frames,) = _COUNT.unpack_from(data)
    mean = np.frombuffer(data, dtype="<f4", offset=_COUNT.size).astype(np.float32)
    if frames < 1 or not np.isfinite(mean).all():
        raise MapCorruptError(f"{what}: a count of {frames} or a mean that is not finite")
    return int(frames), mean


def put_drive_stats(txn: lmdb.Transaction, env: LmdbEnv, seq_id: int, record: bytes) -> None:
    """Store sequence ``seq_id``'s record (:func:`encode_drive_stats`) in ``txn``."""
    txn.put(u32(seq_id), record, db=env.db(DRIVE_STATS_DB))


def get_drive_stats(txn: lmdb.Transaction, env: LmdbEnv, seq_id: int, dim: int
                    ) -> tuple[int, np.ndarray] | None:
    """Sequence ``seq_id``'s ``(frames, mean)``, or None if it has none. O(dim)."""
    if not env.has_db(DRIVE_STATS_DB):  # a map written before statistics, opened read-only
        return None
    raw = txn.get(u32(seq_id), db=env.db(DRIVE_STATS_DB))
    return None if raw is None else decode_drive_stats(raw, dim, f"drive statistics of "
                                                                 f"sequence {seq_id}")


def delete_drive_stats(txn: lmdb.Transaction, env: LmdbEnv, seq_id: int) -> bool:
    """Delete sequence ``seq_id``'s record in ``txn``; whether it had one. O(log n)."""
    if not env.has_db(DRIVE_STATS_DB):
        return False
    return bool(txn.delete(u32(seq_id), db=env.db(DRIVE_STATS_DB)))


def check_drive_stats(txn: lmdb.Transaction, env: LmdbEnv, live: Iterable[int], dim: int
                      ) -> tuple[int, list[str]]:
    """Verify every record against the invariants above: ``(records, problems)``, a problem
    per broken record. O(records * dim)."""
    if not env.has_db(DRIVE_STATS_DB):
        return 0, []
    alive = set(live)
    problems: list[str] = []
    count = 0
    for key, value in txn.cursor(db=env.db(DRIVE_STATS_DB)):
        count += 1
        if len(key) != 4:
            problems.append(f"drive statistics key of {len(key)} bytes")
            continue
        seq_id = int.from_bytes(key, "big")
        if seq_id not in alive:
            problems.append(f"drive statistics of sequence {seq_id}, which is not in the map")
            continue
        try:
            decode_drive_stats(value, dim, f"drive statistics of sequence {seq_id}")
        except MapCorruptError as exc:
            problems.append(str(exc))
    return count, problems


def drop_broken_stats(txn: lmdb.Transaction, env: LmdbEnv, live: Iterable[int], dim: int
                      ) -> int:
    """Delete every record that breaks the invariants (``check --repair``); how many."""
    if not env.has_db(DRIVE_STATS_DB):
        return 0
    alive = set(live)
    broken = []
    for key, value in txn.cursor(db=env.db(DRIVE_STATS_DB)):
        try:
            if len(key) != 4 or int.from_bytes(key, "big") not in alive:
                raise MapCorruptError("stray")
            decode_drive_stats(value, dim)
        except MapCorruptError:
            broken.append(bytes(key))
    for key in broken:
        txn.delete(key, db=env.db(DRIVE_STATS_DB))
    return len(broken)
