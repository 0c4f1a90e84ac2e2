"""The map's plain records: what the store holds and what its operations report.

One module for every record type of the storage layer, so that a caller (the facade, the CLI,
the service, a test) can name a result without importing the operation that makes it:

- committed data: :class:`SequenceRecord` (a drive) and :class:`EdgeRecord` (an edge with its
  provenance), with their LMDB codecs (the byte layouts are in :mod:`sprint_map.storage.keys`);
- input: :class:`EdgeSpec`, an edge to commit with a new sequence;
- results: :class:`AddResult`, :class:`ComponentInfo`, :class:`RemoveResult`,
  :class:`EdgeInfo`, :class:`EdgeTable` (every edge as arrays), :class:`UnmergeResult`, :class:`CompactReport`, :class:`CheckReport`
  (with its :data:`AREAS`) and :class:`RepairReport`.

Every record is a dataclass with no behaviour beyond its codec or its ``to_dict`` (the JSON
contract of the CLI command that prints it). The public ones are re-exported by
:mod:`sprint_map`.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np

from sprint_map.errors import MapCorruptError
from sprint_map.storage.keys import EDGE_KEY, EDGE_VAL, NO_QUERY, Raw, decode_json

__all__ = [
    "AREAS",
    "AddResult",
    "CheckReport",
    "CompactReport",
    "ComponentInfo",
    "EdgeInfo",
    "EdgeRecord",
    "EdgeSpec",
    "EdgeTable",
    "RemoveResult",
    "RepairReport",
    "SequenceRecord",
    "UnmergeResult",
]


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


@dataclass(frozen=True)
class EdgeSpec:
    """An inter-sequence edge to commit with a new sequence.

    ``src`` and ``dst`` are ``(seq_id, image_id)``; ``seq_id`` ``None`` means the sequence
    being added. ``weight`` is the match probability; ``frame`` the query frame that made it.
    """

    src: tuple[int | None, int]
    dst: tuple[int | None, int]
    weight: float = 1.0
    frame: int | None = None


@dataclass(frozen=True)
class AddResult:
    """What :meth:`sprint_map.storage.store.MapStore.add_sequence` committed."""

    sequence: SequenceRecord
    component: int
    edges_added: int
    #: The sequence was already committed under this name with the very same descriptors (a
    #: retry after a failure past the commit point): nothing was added.
    already_committed: bool = False


@dataclass(frozen=True)
class ComponentInfo:
    """One connected component of the map: its id (the union-find root sequence), its
    sequences and their total vertex count."""

    component: int
    sequences: list[int]
    vertices: int


@dataclass(frozen=True)
class RemoveResult:
    """What :func:`sprint_map.storage.removal.remove_sequences` committed."""

    removed: list[SequenceRecord]
    edges_removed: int
    #: Components before the removal that held a removed sequence.
    components_affected: list[int]
    #: The components their remaining sequences form now (ids = union-find roots).
    components_after: list[int]

    def to_dict(self) -> dict[str, Any]:
        return {
            "removed": [{"seq_id": s.seq_id, "name": s.name, "frames": s.length}
                        for s in self.removed],
            "vertices_removed": sum(s.length for s in self.removed),
            "edges_removed": self.edges_removed,
            "components_affected": self.components_affected,
            "components_after": self.components_after,
        }


@dataclass(frozen=True)
class EdgeInfo:
    """One directed edge between ``(seq, image)`` endpoints, with its provenance.

    ``added_by`` is the sequence whose commit wrote the edge (None for an edge written without
    one); ``frame`` the query frame of that drive that made it (None if not given).
    """

    src_seq: int
    src_image: int
    dst_seq: int
    dst_image: int
    prob: float
    added_by: int | None
    frame: int | None
    time: float

    def to_dict(self) -> dict[str, Any]:
        """The JSON contract of ``sprint-map edges --json``: exactly these six keys."""
        return {"src_seq": self.src_seq, "src_image": self.src_image, "dst_seq": self.dst_seq,
                "dst_image": self.dst_image, "prob": self.prob, "added_by": self.added_by}


@dataclass(frozen=True)
class UnmergeResult:
    """What :func:`sprint_map.storage.provenance.unmerge_sequence` committed.

    ``components`` are the ids of the components that the affected ones (those that held a
    revoked edge) form afterwards, ascending; empty when nothing was revoked. The map's total
    is in ``stats()``.
    """

    seq_id: int
    edges_removed: int
    components: list[int]

    def to_dict(self) -> dict[str, Any]:
        """The JSON contract of ``sprint-map unmerge --json``: exactly these three keys."""
        return {"seq_id": self.seq_id, "edges_removed": self.edges_removed,
                "components": self.components}


@dataclass(frozen=True)
class CompactReport:
    """What :func:`sprint_map.storage.compaction.compact_map` did; byte counts are allocated
    blocks of the map directory."""

    generation: str
    sequences: int
    vertices_before: int
    vertices_after: int
    bytes_before: int
    bytes_after: int
    #: bytes of each part of the old and the new generation (lmdb, shards, index)
    parts_before: dict[str, int]
    parts_after: dict[str, int]
    #: False if a reader still had the old generation open (the next writer's open removes it)
    old_generation_removed: bool
    seconds: float

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


#: What each area of the invariants covers.
AREAS = {
    "sequences": "sequence records tile the vertex ids 0..next_vertex_id-1 (source of truth)",
    "lookup": "name and vertex-range indexes, next_seq_id and n_sequences",
    "shard_files": "shard files hold every committed row, equal to the digest committed with "
                   "its sequence",
    "shard_lengths": "committed shard lengths recorded in LMDB",
    "edges": "edge endpoints exist and join two sequences; edge values and their provenance",
    "edge_index": "reverse edge index and n_edges",
    "components": "union-find, membership lists, totals and n_components",
    "index": "the persisted FAISS index",
    "temp": "leftover temp files",
    "removed": "removed vertex ranges hold no positions; the removed_vertices counter",
    "thumbnails": "thumbnails name frames of live sequences, are JPEG bytes, and a sequence "
                  "has one per frame or none",
    "sightings": "records of places seen again (admission) name frames of live sequences and "
                 "decode",
    "drive_stats": "drive statistics (frames, mean descriptor) name live sequences, have the "
                   "map's dimension and are finite",
}


@dataclass
class CheckReport:
    """Result of :func:`sprint_map.storage.check.check_map`: ``ok`` when ``violations`` is empty.

    ``areas`` names the :data:`AREAS` with at least one violation.
    """

    violations: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    checked: dict[str, int] = field(default_factory=dict)
    areas: set[str] = field(default_factory=set)

    @property
    def ok(self) -> bool:
        return not self.violations

    def violation(self, area: str, message: str) -> None:
        assert area in AREAS, area
        self.violations.append(message)
        self.areas.add(area)

    def to_dict(self) -> dict[str, Any]:
        return {"ok": self.ok, "violations": self.violations, "notes": self.notes,
                "checked": self.checked, "areas": sorted(self.areas)}


@dataclass
class RepairReport:
    """What :func:`sprint_map.storage.repair.repair_map` found after the writer's open
    (``found``), did (``repaired``, the open's recovery included) and declined to do
    (``skipped``), and the check of the map afterwards (``after``): ``ok`` when the map is now
    healthy."""

    found: list[str] = field(default_factory=list)
    repaired: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    after: CheckReport = field(default_factory=CheckReport)

    @property
    def ok(self) -> bool:
        return self.after.ok

    def to_dict(self) -> dict[str, Any]:
        return {"ok": self.ok, "found": self.found, "repaired": self.repaired,
                "skipped": self.skipped, "unrepaired": self.after.violations,
                "after": self.after.to_dict()}


@dataclass(frozen=True)
class EdgeTable:
    """Every edge as parallel arrays, in (src, dst) vertex order: ``src``, ``dst`` (global
    vertex ids, int64), ``prob`` (float64), ``added_by`` (int64, -1 for none)."""

    src: np.ndarray
    dst: np.ndarray
    prob: np.ndarray
    added_by: np.ndarray

    def __len__(self) -> int:
        return len(self.src)

    @classmethod
    def decode(cls, keys: Sequence[Raw], values: Sequence[Raw]) -> EdgeTable:
        """The edges of raw LMDB ``keys`` and ``values`` (as a cursor gives them), decoded with
        numpy, not a record object per edge; MapCorruptError for a record of the wrong size.

        Notes
        -----
        O(E), about 40 bytes per edge: a few C-level passes over the joined bytes.
        """
        if set(map(len, keys)) - {EDGE_KEY.size} or set(map(len, values)) - {EDGE_VAL.size}:
            raise MapCorruptError("corrupt edge record: wrong key or value size")
        k = np.frombuffer(b"".join(keys), dtype=_EDGE_KEY_DTYPE)
        v = np.frombuffer(b"".join(values), dtype=_EDGE_VAL_DTYPE)
        query = v["query"].astype(np.int64)
        query[query == NO_QUERY] = -1
        return cls(k["src"].astype(np.int64), k["dst"].astype(np.int64),
                   v["prob"].astype(np.float64), query)


#: An edge key and value as numpy records (big-endian, as stored: EDGE_KEY, EDGE_VAL).
_EDGE_KEY_DTYPE = np.dtype([("src", ">u8"), ("dst", ">u8")])
_EDGE_VAL_DTYPE = np.dtype([("prob", ">f8"), ("query", ">u4"), ("frame", ">u4"), ("time", ">f8")])
assert _EDGE_KEY_DTYPE.itemsize == EDGE_KEY.size and _EDGE_VAL_DTYPE.itemsize == EDGE_VAL.size
