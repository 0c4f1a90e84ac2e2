"""Places seen again: what a map with admission records instead of storing a redundant frame.

A map created with ``--admission novel`` (:mod:`sprint_map.merge.admission`) does not store
the frames of a drive that it matched confidently and redundantly; it records, for each stored
vertex such a frame matched, that the place was seen again. The ``sightings`` LMDB database
holds one record per vertex ever seen again, keyed by ``(seq_id, image_id)``
(:data:`SIGHT_KEY`, big-endian, so a sequence's sightings are one key range), with

- ``count``: how many frames of later drives matched it (and were not stored);
- ``last_seen``: when the last of them was committed (Unix seconds);
- ``last_distance``: that frame's squared-L2 descriptor distance to the vertex (how alike
  it looked: the appearance it was seen under, on the descriptor's scale);
- ``last_drive``: that drive's name.

They are written in the transaction that commits the drive (the commit point: a drive's
sightings count whole or not at all), deleted with the sequence they name, copied as they are
by ``compact`` (sequence ids are kept) and verified by ``check`` (area ``sightings``: every key
names a frame of a live sequence, every value decodes). They are statistics, not belief: the
HMM never reads them, ``unmerge`` leaves them, and ``check --repair`` drops the stray ones.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable
from dataclasses import dataclass, field

import lmdb

from sprint_map.errors import MapCorruptError
from sprint_map.storage.keys import SEQ_IMAGE_KEY, sequence_keys
from sprint_map.storage.lmdb_env import LmdbEnv

__all__ = ["SIGHTINGS_DB", "SIGHT_KEY", "Sighting", "SightingScan", "decode_sighting",
           "delete_sightings", "drop_stray_sightings", "encode_sighting", "get_sighting",
           "record_sightings", "scan_sightings"]

SIGHTINGS_DB = "sightings"
#: ``(seq_id, image_id)`` of the vertex seen again.
SIGHT_KEY = SEQ_IMAGE_KEY
#: count, last_seen, last_distance; the last drive's name (UTF-8) follows.
_SIGHT_HEAD = struct.Struct(">Idf")


@dataclass(frozen=True)
class Sighting:
    """One vertex's record of being seen again (see the module docstring)."""

    seq_id: int
    image_id: int
    count: int
    last_seen: float
    last_distance: float
    last_drive: str

    def to_dict(self) -> dict[str, object]:
        return {"seq_id": self.seq_id, "image_id": self.image_id, "count": self.count,
                "last_seen": self.last_seen, "last_distance": self.last_distance,
                "last_drive": self.last_drive}


def decode_sighting(key: bytes, value: bytes) -> Sighting:
    """One record of the ``sightings`` database (MapCorruptError if it does not decode)."""
    seq_id, image_id = SIGHT_KEY.unpack(key)
    if len(value) < _SIGHT_HEAD.size:
        raise MapCorruptError(f"sighting of sequence {seq_id} image {image_id} is "
                              f"{len(value)} bytes")
    count, seen, dist = _SIGHT_HEAD.unpack_from(value)
    try:
        drive = bytes(value[_SIGHT_HEAD.size:]).decode()
    except UnicodeDecodeError as exc:
        raise MapCorruptError(f"sighting of sequence {seq_id} image {image_id}: drive name "
                              "is not UTF-8") from exc
    return Sighting(seq_id, image_id, count, seen, dist, drive)


def encode_sighting(count: int, last_seen: float, last_distance: float, last_drive: str
                    ) -> bytes:
    """The value of one sighting record."""
    return _SIGHT_HEAD.pack(count, float(last_seen), float(last_distance)) + last_drive.encode()


def record_sightings(txn: lmdb.Transaction, env: LmdbEnv,
                     seen: Iterable[tuple[int, int, float]], drive: str, when: float) -> int:
    """Count, in ``txn``, one sighting per ``(seq_id, image_id, distance)`` by drive
    ``drive`` at ``when``; a vertex named twice counts twice (the last distance is kept).
    Returns the number counted. O(m log n) for m sightings."""
    db = env.db(SIGHTINGS_DB)
    counted = 0
    for seq_id, image_id, distance in seen:
        key = SIGHT_KEY.pack(int(seq_id), int(image_id))
        raw = txn.get(key, db=db)
        count = 0 if raw is None else decode_sighting(key, bytes(raw)).count
        txn.put(key, encode_sighting(min(count + 1, 2**32 - 1), when, distance, drive), db=db)
        counted += 1
    return counted


def get_sighting(txn: lmdb.Transaction, env: LmdbEnv, seq_id: int, image_id: int
                 ) -> Sighting | None:
    """The sighting record of vertex ``(seq_id, image_id)``, or None. O(log n)."""
    if not env.has_db(SIGHTINGS_DB):  # a map written before admission, opened read-only
        return None
    key = SIGHT_KEY.pack(seq_id, image_id)
    raw = txn.get(key, db=env.db(SIGHTINGS_DB))
    return None if raw is None else decode_sighting(key, bytes(raw))


def delete_sightings(txn: lmdb.Transaction, env: LmdbEnv, seq_id: int) -> int:
    """Delete sequence ``seq_id``'s sighting records in ``txn``; return how many.
    O(log n + its records)."""
    if not env.has_db(SIGHTINGS_DB):
        return 0
    keys = sequence_keys(txn, env.db(SIGHTINGS_DB), seq_id)
    for key in keys:
        txn.delete(key, db=env.db(SIGHTINGS_DB))
    return len(keys)


@dataclass
class SightingScan:
    """What :func:`scan_sightings` found."""

    #: sighting records per live sequence that has any
    records: dict[int, int] = field(default_factory=dict)
    #: sightings counted in all
    total: int = 0
    #: one message per problem
    problems: list[str] = field(default_factory=list)
    #: keys that name no frame of a live sequence, or whose value does not decode
    stray_keys: list[bytes] = field(default_factory=list)


def scan_sightings(txn: lmdb.Transaction, env: LmdbEnv, lengths: dict[int, int]
                   ) -> SightingScan:
    """Check every sighting against the live sequences ``lengths`` (seq_id -> frames).

    Notes
    -----
    One cursor pass: O(records) reads, O(sequences) memory.
    """
    scan = SightingScan()
    if not env.has_db(SIGHTINGS_DB):
        return scan
    for key, value in txn.cursor(db=env.db(SIGHTINGS_DB)):
        try:
            seen = decode_sighting(bytes(key), bytes(value))
        except MapCorruptError as exc:
            scan.stray_keys.append(bytes(key))
            scan.problems.append(f"sighting record {bytes(key).hex()}: {exc}")
            continue
        length = lengths.get(seen.seq_id)
        if length is None or seen.image_id >= length:
            scan.stray_keys.append(bytes(key))
            where = "no sequence" if length is None else f"{length} frames"
            scan.problems.append(f"sighting of sequence {seen.seq_id} image {seen.image_id} "
                                 f"names no frame of the map ({where})")
            continue
        if seen.count < 1:
            scan.stray_keys.append(bytes(key))
            scan.problems.append(f"sighting of sequence {seen.seq_id} image {seen.image_id} "
                                 "counts no sighting")
            continue
        scan.records[seen.seq_id] = scan.records.get(seen.seq_id, 0) + 1
        scan.total += seen.count
    return scan


def drop_stray_sightings(txn: lmdb.Transaction, env: LmdbEnv, lengths: dict[int, int]
                         ) -> list[str]:
    """Delete, in ``txn``, the sighting records :func:`scan_sightings` finds broken (they are
    statistics: nothing is lost that belief needs). Returns what was done. O(records)."""
    scan = scan_sightings(txn, env, lengths)
    for key in scan.stray_keys:
        txn.delete(key, db=env.db(SIGHTINGS_DB))
    if scan.stray_keys:
        return [f"dropped {len(scan.stray_keys)} sighting records that name no frame of the "
                "map or do not decode"]
    return []
