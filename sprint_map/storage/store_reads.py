"""StoreReads: what a map store reads of its committed records (the meta counters, sequences,
vertices, positions, the geographic frame, thumbnails, sightings, components and edges).

A mixin of :class:`~sprint_map.storage.store.MapStore` over its LMDB environment, shards and
union-find; every read runs in one LMDB read transaction (a consistent snapshot), its own or
the caller's ``txn``. Nothing here writes.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import lmdb
import numpy as np

from sprint_map.errors import MapCorruptError, UnknownSequenceError
from sprint_map.storage.components import ComponentStore
from sprint_map.storage.drive_stats import get_drive_stats
from sprint_map.storage.keys import (
    EDGE_KEY,
    VERTEX_VAL,
    Raw,
    decode_json,
    decode_vertex,
    read_u32,
    read_u64,
    u32,
    u64,
)
from sprint_map.storage.lmdb_env import LmdbEnv
from sprint_map.storage.records import ComponentInfo, EdgeRecord, EdgeTable, SequenceRecord
from sprint_map.storage.shards import ShardSet
from sprint_map.storage.sightings import Sighting, get_sighting
from sprint_map.storage.thumbnails import count_thumbnails, get_thumbnail
from sprint_map.util.arrays import Descriptors, Float64Array
from sprint_map.util.validation import name_key, shown

__all__ = ["StoreReads"]


class StoreReads:
    """Reads of a map's committed records (see the module docstring); the store provides
    ``env``, ``shards`` and ``uf``."""

    env: LmdbEnv
    shards: ShardSet
    uf: ComponentStore

    def counter(self, name: str, txn: lmdb.Transaction | None = None) -> int:
        if txn is None:
            with self.env.read() as txn:
                return self.counter(name, txn)
        raw = txn.get(name.encode(), db=self.env.db("meta"))
        if raw is None:
            raise MapCorruptError(f"meta record {name!r} is missing")
        if len(raw) != 8:
            raise MapCorruptError(f"corrupt map record {name}: {len(raw)} bytes, not 8")
        return read_u64(raw)

    def sequence(self, seq_id: int, txn: lmdb.Transaction | None = None) -> SequenceRecord:
        """The record of sequence ``seq_id``. O(log n_sequences)."""
        if txn is None:
            with self.env.read() as txn:
                return self.sequence(seq_id, txn)
        raw = txn.get(u32(seq_id), db=self.env.db("sequences")) if 0 <= seq_id < 2**32 else None
        if raw is None:
            raise UnknownSequenceError(f"no sequence {seq_id} in the map")
        return SequenceRecord.decode(raw)

    def sequence_by_name(self, name: str) -> SequenceRecord:
        """The record of the sequence named ``name``. O(log n_sequences).

        Raises
        ------
        UnknownSequenceError
            No sequence has that name (none can have ``""`` or a name with a newline).
        InputError
            ``name`` is not UTF-8 text.
        """
        key = name_key(name)
        with self.env.read() as txn:
            raw = None if key is None else txn.get(key, db=self.env.db("seq_names"))
            if raw is None:
                raise UnknownSequenceError(f"no sequence named {shown(name)} in the map")
            return self.sequence(read_u32(raw), txn)

    def sequences(self) -> list[SequenceRecord]:
        """All sequence records in id order. O(n_sequences)."""
        with self.env.read() as txn:
            return [SequenceRecord.decode(v) for _, v in txn.cursor(db=self.env.db("sequences"))]

    def locate(self, vertex_ids: Iterable[int], txn: lmdb.Transaction | None = None
               ) -> list[tuple[int, int]]:
        """``(seq_id, image_id)`` of each vertex id. O(log n_sequences) per vertex."""
        if txn is None:
            with self.env.read() as txn:
                return self.locate(vertex_ids, txn)
        total = self.counter("next_vertex_id", txn)
        cursor = txn.cursor(db=self.env.db("vrange"))
        out = []
        for vid in vertex_ids:
            vid = int(vid)
            if not 0 <= vid < total:
                raise MapCorruptError(f"vertex {vid} is not in the map")
            # Past the last live sequence, or before the one found: a removed range.
            seq = self.sequence(read_u32(cursor.value()), txn) if cursor.set_range(
                u64(vid)) else None
            if seq is None or vid < seq.first_vertex:
                raise UnknownSequenceError(f"vertex {vid} belonged to a removed sequence")
            out.append((seq.seq_id, vid - seq.first_vertex))
        return out

    def vertex_id(self, seq_id: int, image_id: int, txn: lmdb.Transaction | None = None) -> int:
        seq = self.sequence(seq_id, txn)
        if not 0 <= image_id < seq.length:
            raise UnknownSequenceError(
                f"sequence {seq_id} has no image {image_id} (it has {seq.length})"
            )
        return seq.first_vertex + image_id

    def descriptors(self, seq_id: int) -> Descriptors:
        """The descriptors of a sequence (a read-only memory-mapped view when in one shard)."""
        with self.env.read() as txn:
            seq = self.sequence(seq_id, txn)
            total = self.counter("next_vertex_id", txn)
        return self.shards.rows(seq.first_vertex, seq.first_vertex + seq.length, total)

    def positions(self, seq_id: int) -> Float64Array | None:
        """Per-vertex ``(x, y, heading, timestamp)`` of a sequence, with a fifth column
        ``sigma_m`` when any of its fixes has an accuracy; NaN rows for frames without a fix;
        None if none were given. O(length) reads."""
        with self.env.read() as txn:
            seq = self.sequence(seq_id, txn)
            db = self.env.db("vertex_data")
            cursor = txn.cursor(db=db)
            last = u64(seq.last_vertex)
            if not cursor.set_range(u64(seq.first_vertex)) or bytes(cursor.key()) > last:
                return None
            # raw records gathered, then decoded at once (per record: ~10x less Python)
            keys, values = [], []
            wide = False
            for key, value in cursor:
                if len(key) != 8 or bytes(key) > last:  # fixed-width big-endian: as the ids
                    if len(key) != 8:
                        read_u64(key)  # a corrupt key: its error
                    break
                if len(value) != VERTEX_VAL.size:
                    decode_vertex(value)  # a corrupt record raises; else the sigma form
                    wide = True
                keys.append(key)
                values.append(value)
            vids = np.frombuffer(b"".join(keys), dtype=">u8").astype(np.int64)
            out = np.full((seq.length, 5 if wide else 4), np.nan)
            if not wide:
                out[vids - seq.first_vertex] = np.frombuffer(b"".join(values), dtype=">f8"
                                                             ).reshape(-1, 4)
            else:
                out[vids - seq.first_vertex] = [decode_vertex(v) for v in values]
        return out

    def has_positions(self) -> bool:
        """Whether any vertex (of a live or a removed sequence, until ``compact``) has a
        position. O(1)."""
        with self.env.read() as txn:
            return bool(txn.cursor(db=self.env.db("vertex_data")).first())

    def geo_frame(self) -> dict[str, Any] | None:
        """The geographic frame record the map keeps its latitude/longitude positions in
        (a JSON object; its meaning is the caller's), or None. O(1)."""
        with self.env.read() as txn:
            raw = txn.get(b"geo_frame", db=self.env.db("meta"))
        if raw is None:
            return None
        record = decode_json(raw, "geo_frame")
        if not isinstance(record, dict):
            raise MapCorruptError("corrupt geo_frame record: not a JSON object")
        return record

    def thumbnail(self, seq_id: int, image_id: int) -> bytes | None:
        """The JPEG thumbnail of frame ``image_id`` of sequence ``seq_id``, or None if the
        drive was added without thumbnails. O(log n).

        Raises
        ------
        UnknownSequenceError
            No such sequence, or no such frame in it.
        """
        with self.env.read() as txn:
            self.vertex_id(seq_id, image_id, txn)
            return get_thumbnail(txn, self.env, seq_id, image_id)

    def sighting(self, seq_id: int, image_id: int) -> Sighting | None:
        """The record of vertex ``(seq_id, image_id)`` being seen again, or None. O(log n).

        Raises
        ------
        UnknownSequenceError
            No such sequence, or no such frame in it.
        """
        with self.env.read() as txn:
            self.vertex_id(seq_id, image_id, txn)
            return get_sighting(txn, self.env, seq_id, image_id)

    def drive_stats(self, seq_id: int) -> tuple[int, np.ndarray] | None:
        """Sequence ``seq_id``'s ``(frames, mean)`` (:mod:`sprint_map.storage.drive_stats`), or
        None if it was written without. O(dim).

        Raises
        ------
        UnknownSequenceError
            No such sequence.
        """
        with self.env.read() as txn:
            self.sequence(seq_id, txn)
            return get_drive_stats(txn, self.env, seq_id, self.shards.dim)

    def all_drive_stats(self) -> list[tuple[int, int, np.ndarray]]:
        """``(seq_id, frames, mean)`` of every sequence with statistics. O(sequences * dim)."""
        from sprint_map.storage.drive_stats import DRIVE_STATS_DB, decode_drive_stats

        if not self.env.has_db(DRIVE_STATS_DB):
            return []
        with self.env.read() as txn:
            return [(read_u32(k), *decode_drive_stats(v, self.shards.dim))
                    for k, v in txn.cursor(db=self.env.db(DRIVE_STATS_DB))]

    def thumbnail_count(self, seq_id: int) -> int:
        """Thumbnails sequence ``seq_id`` keeps: its length, or 0. O(log n + count)."""
        with self.env.read() as txn:
            self.sequence(seq_id, txn)
            return count_thumbnails(txn, self.env, seq_id)

    def component_of(self, seq_id: int, txn: lmdb.Transaction | None = None) -> int:
        """Component id (union-find root sequence) of ``seq_id``. O(alpha(n)) amortised."""
        if txn is None:
            with self.env.read() as txn:
                return self.component_of(seq_id, txn)
        self.sequence(seq_id, txn)
        return self.uf.find(txn, seq_id)

    def components(self) -> list[ComponentInfo]:
        """Every component with its sequences and vertex count. O(n_sequences)."""
        with self.env.read() as txn:
            return [
                ComponentInfo(root, self.uf.members(txn, root), verts)
                for root, _, verts in self.uf.components(txn)
            ]

    def component_sequences(self, root: int, txn: lmdb.Transaction) -> list[SequenceRecord]:
        return [self.sequence(s, txn) for s in self.uf.members(txn, root)]

    def edges_from(self, first: int, last: int, txn: lmdb.Transaction | None = None
                   ) -> list[EdgeRecord]:
        """Edges whose source vertex lies in ``first..last``. O(log E + edges returned)."""
        if txn is None:
            with self.env.read() as txn:
                return self.edges_from(first, last, txn)
        out = []
        cursor = txn.cursor(db=self.env.db("edges"))
        if cursor.set_range(EDGE_KEY.pack(first, 0)):
            for key, value in cursor:
                if EDGE_KEY.unpack(key)[0] > last:
                    break
                out.append(EdgeRecord.decode(key, value))
        return out

    def edge_table_from(self, ranges: Iterable[tuple[int, int]], txn: lmdb.Transaction
                        ) -> EdgeTable:
        """Edges whose source vertex lies in one of the ``(first, last)`` ranges, as arrays
        (:meth:`edges_from` without a record object per edge), range by range.

        Notes
        -----
        O(R log E + E_r) for R ranges and the E_r edges returned: one cursor seek per range,
        then raw keys and values joined and decoded with numpy.
        """
        keys: list[Raw] = []
        values: list[Raw] = []
        cursor = txn.cursor(db=self.env.db("edges"))
        for first, last in ranges:
            if not cursor.set_range(EDGE_KEY.pack(first, 0)):
                continue
            stop = u64(last)  # big-endian: byte order is numeric order
            for key, value in cursor.iternext():
                if bytes(key[:8]) > stop:
                    break
                keys.append(key)
                values.append(value)
        return EdgeTable.decode(keys, values)

    def edges(self) -> list[EdgeRecord]:
        """Every edge. O(E): for export and checks, not for queries."""
        with self.env.read() as txn:
            return [EdgeRecord.decode(k, v) for k, v in txn.cursor(db=self.env.db("edges"))]
