"""Binary key and record codecs for the LMDB databases.

Keys are big-endian fixed-width integers so that LMDB's byte order is numeric order: this allows
``append=True`` bulk loads, range scans (all out-edges of a vertex range) and floor look-ups
(vertex id -> sequence) with a single cursor seek.

Every decode of an LMDB record goes through this module (:class:`RecordStruct`, :func:`read_u32`,
:func:`read_u64`, :meth:`SequenceRecord.decode`, :meth:`EdgeRecord.decode`,
:func:`decode_text`, :func:`decode_number`), and each raises
:class:`~sprint_map.errors.MapCorruptError` for a record that is not what its database holds: a
corrupt record is the corrupt-map error (exit 7), never a ``struct.error`` or ``ValueError``.
"""

from __future__ import annotations

import json
import math
import struct
from dataclasses import asdict, dataclass, fields
from typing import Any

from sprint_map.errors import MapCorruptError


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

#: removed vertex range, keyed by its last vertex: first vertex, seq id it belonged to
REMOVED_VAL = RecordStruct(">QI")
#: content digest of a sequence's descriptor rows (``digests`` database): BLAKE2b, 16 bytes
DIGEST_BYTES = 16

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


@dataclass(frozen=True)
class SequenceRecord:
    """One committed sequence (drive). Its vertices are ``first_vertex .. first_vertex+length-1``."""

    seq_id: int
    name: str
    length: int
    first_vertex: int
    created: float
    source: str = ""

    @property
    def last_vertex(self) -> int:
        return self.first_vertex + self.length - 1

    def encode(self) -> bytes:
        return json.dumps(asdict(self), separators=(",", ":")).encode()

    @classmethod
    def decode(cls, raw: Raw) -> SequenceRecord:
        """Parse a record; MapCorruptError unless every field is there with its type.

        Unknown keys are ignored (a newer writer may add fields). O(len(raw)).
        """
        data = decode_json(raw, "of a sequence")
        if not isinstance(data, dict):
            raise MapCorruptError("corrupt sequence record: not a JSON object")
        values: dict[str, Any] = {}
        for f in fields(cls):
            if f.name not in data:
                if f.name == "source":
                    continue
                raise MapCorruptError(f"corrupt sequence record: no {f.name!r}")
            value = data[f.name]
            want = _FIELD_TYPES[f.name]
            if isinstance(value, bool) or not isinstance(value, want):
                raise MapCorruptError(f"corrupt sequence record: {f.name!r} is {value!r}")
            values[f.name] = value
        record = cls(**values)
        if record.seq_id < 0 or record.length < 0 or record.first_vertex < 0:
            raise MapCorruptError(f"corrupt sequence record {record.seq_id}: negative ids")
        return record


_FIELD_TYPES: dict[str, type | tuple[type, ...]] = {
    "seq_id": int, "name": str, "length": int, "first_vertex": int, "created": (int, float),
    "source": str}


@dataclass(frozen=True)
class EdgeRecord:
    """A directed inter-sequence edge with its provenance."""

    src: int
    dst: int
    weight: float
    query_seq: int | None
    frame: int | None
    time: float

    def encode_value(self) -> bytes:
        query = NO_QUERY if self.query_seq is None else self.query_seq
        frame = NO_QUERY if self.frame is None else self.frame
        return EDGE_VAL.pack(self.weight, query, frame, self.time)

    @classmethod
    def decode(cls, key: Raw, value: Raw) -> EdgeRecord:
        src, dst = EDGE_KEY.unpack(key)
        weight, query, frame, when = EDGE_VAL.unpack(value)
        return cls(
            src=src,
            dst=dst,
            weight=weight,
            query_seq=None if query == NO_QUERY else query,
            frame=None if frame == NO_QUERY else frame,
            time=when,
        )
