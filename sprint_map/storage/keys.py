"""Binary key and record codecs for the LMDB databases.

Keys are big-endian fixed-width integers so that LMDB's byte order is numeric order: this allows
``append=True`` bulk loads, range scans (all out-edges of a vertex range) and floor look-ups
(vertex id -> sequence) with a single cursor seek.
"""

from __future__ import annotations

import json
import struct
from dataclasses import asdict, dataclass
from typing import Any

U32 = struct.Struct(">I")
U64 = struct.Struct(">Q")
#: (src vertex, dst vertex): edges and the reverse index
EDGE_KEY = struct.Struct(">QQ")
#: edge provenance: weight (prob), query sequence that created it, frame, unix time
EDGE_VAL = struct.Struct(">dIId")
#: union-find row of a sequence: parent sequence id, component size in sequences (valid at roots)
UF_VAL = struct.Struct(">II")
#: per-component totals kept at the root: sequences, vertices
COMP_VAL = struct.Struct(">QQ")
#: optional per-vertex data: x, y, heading (deg, NaN if unknown), timestamp (NaN if unknown)
VERTEX_VAL = struct.Struct(">dddd")

#: removed vertex range, keyed by its last vertex: first vertex, seq id it belonged to
REMOVED_VAL = struct.Struct(">QI")

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
        data: dict[str, Any] = json.loads(bytes(raw))
        return cls(**data)


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
