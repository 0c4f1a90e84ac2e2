"""Binary key and record codecs for the LMDB databases.

Keys are big-endian fixed-width integers so that LMDB's byte order is numeric order: this allows
``append=True`` bulk loads, range scans (all out-edges of a vertex range) and floor look-ups
(vertex id -> sequence) with a single cursor seek.

Every decode of an LMDB record goes through this module (:class:`RecordStruct`, :func:`read_u32`,
:func:`read_u64`, :func:`decode_text`, :func:`decode_number`, :func:`decode_json`, and the
record classes' codecs built on them: ``SequenceRecord.decode`` and ``EdgeRecord.decode`` in
:mod:`sprint_map.storage.records`), and each raises
:class:`~sprint_map.errors.MapCorruptError` for a record that is not what its database holds: a
corrupt record is the corrupt-map error (exit 7), never a ``struct.error`` or ``ValueError``.
"""

from __future__ import annotations

import json
import math
import struct
from typing import Any

from sprint_map.errors import MapCorruptError

__all__ = ["COMP_VAL", "DIGEST_BYTES", "EDGE_KEY", "EDGE_VAL", "NO_QUERY", "REMOVED_VAL", "Raw",
           "RecordStruct", "SEQ_IMAGE_KEY", "THUMB_KEY", "U32", "U64", "UF_VAL", "VERTEX_VAL", "VERTEX_VAL_SIGMA",
           "decode_json", "decode_vertex",
           "decode_number", "decode_text", "read_u32", "read_u64", "sequence_keys", "u32", "u64"]


class RecordStruct(struct.Struct):
    """A fixed-width LMDB key or value layout whose ``unpack`` raises MapCorruptError.

    A record of the wrong length (a torn or garbled LMDB page, a record of another database)
    is corruption of the map, reported as such wherever it is read. O(1).
    """

    def unpack(self, buffer: Any) -> tuple[Any, ...]:
        try:
            return super().unpack(buffer)
        except struct.error as exc:
            raise MapCorruptError(f"corrupt map record: {len(buffer)} bytes where the "
                                  f"layout {self.format!r} takes {self.size}") from exc


U32 = RecordStruct(">I")
U64 = RecordStruct(">Q")
#: (src vertex, dst vertex): edges and the reverse index
EDGE_KEY = RecordStruct(">QQ")
#: edge provenance: weight (prob), query sequence that created it, frame, unix time
EDGE_VAL = RecordStruct(">dIId")
#: union-find row of a sequence: parent sequence id, component size in sequences (valid at roots)
UF_VAL = RecordStruct(">II")
#: per-component totals kept at the root: sequences, vertices
COMP_VAL = RecordStruct(">QQ")
#: optional per-vertex data: x, y, heading (deg, NaN if unknown), timestamp (NaN if unknown)
VERTEX_VAL = RecordStruct(">dddd")
#: the same with the fix's accuracy (sigma, metres) after it: written only for a vertex that
#: has one, so a map without accuracies keeps the 32-byte records (and older readers)
VERTEX_VAL_SIGMA = RecordStruct(">ddddd")


def decode_vertex(raw: Raw) -> tuple[float, float, float, float, float]:
    """``x, y, heading, timestamp, sigma`` of a ``vertex_data`` value of either width (sigma
    NaN for the 32-byte form); MapCorruptError for any other width. O(1)."""
    if len(raw) == VERTEX_VAL.size:
        x, y, heading, when = VERTEX_VAL.unpack(raw)
        return x, y, heading, when, float("nan")
    x, y, heading, when, sigma = VERTEX_VAL_SIGMA.unpack(raw)
    return x, y, heading, when, sigma

#: removed vertex range, keyed by its last vertex: first vertex, seq id it belonged to
REMOVED_VAL = RecordStruct(">QI")
#: content digest of a sequence's descriptor rows (``digests`` database): BLAKE2b, 16 bytes
DIGEST_BYTES = 16
#: a per-frame record keyed ``(sequence id, image id)``: a sequence's records are one key range
SEQ_IMAGE_KEY = RecordStruct(">II")
#: a frame's thumbnail (``thumbnails`` database): sequence id, image id -> JPEG bytes
THUMB_KEY = SEQ_IMAGE_KEY


def sequence_keys(txn: Any, db: Any, seq_id: int) -> list[bytes]:
    """The keys of sequence ``seq_id`` in a database keyed by :data:`SEQ_IMAGE_KEY` (the
    ``thumbnails`` and ``sightings`` databases): one seek and a range scan, O(log n + count)."""
    out: list[bytes] = []
    cursor = txn.cursor(db=db)
    if cursor.set_range(SEQ_IMAGE_KEY.pack(seq_id, 0)):
        for key in cursor.iternext(keys=True, values=False):
            if len(key) != SEQ_IMAGE_KEY.size or SEQ_IMAGE_KEY.unpack(key)[0] != seq_id:
                break
            out.append(bytes(key))
    return out

NO_QUERY = 0xFFFFFFFF  # provenance query id for edges given directly, not by a localisation

#: What py-lmdb hands back for a key or value (memoryview when a txn uses ``buffers=True``).
Raw = bytes | memoryview


def u32(value: int) -> bytes:
    return U32.pack(value)


def u64(value: int) -> bytes:
    return U64.pack(value)


def read_u32(raw: Raw) -> int:
    return int(U32.unpack(raw)[0])


def read_u64(raw: Raw) -> int:
    return int(U64.unpack(raw)[0])


def decode_text(raw: Raw, what: str) -> str:
    """A UTF-8 record (a name, a meta value) or MapCorruptError naming ``what``. O(len)."""
    try:
        return bytes(raw).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise MapCorruptError(f"corrupt map record {what}: not UTF-8 text") from exc


def decode_number(raw: Raw, what: str, kind: type[int] | type[float] = int) -> Any:
    """A number stored as ASCII text (``schema_version``, ``created``) or MapCorruptError."""
    text = decode_text(raw, what).strip()
    try:
        value = kind(text)
    except ValueError as exc:
        raise MapCorruptError(f"corrupt map record {what}: {text[:40]!r} is not "
                              f"{'an integer' if kind is int else 'a number'}") from exc
    if kind is float and not math.isfinite(value):
        raise MapCorruptError(f"corrupt map record {what}: {text[:40]!r} is not finite")
    return value


def decode_json(raw: Raw, what: str) -> Any:
    """A JSON record (the config, a sequence record) or MapCorruptError naming ``what``."""
    try:
        return json.loads(decode_text(raw, what))
    except (json.JSONDecodeError, RecursionError) as exc:
        raise MapCorruptError(f"corrupt map record {what}: not JSON ({exc})") from exc


