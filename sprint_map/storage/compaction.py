"""``compact``: reclaim the space of removed sequences by writing a new generation of the map.

Removal (:mod:`sprint_map.storage.removal`) leaves the descriptors of removed vertices in the
shards and the index, their ids in the id space, and LMDB's freed pages in its file (LMDB never
shrinks a file). Compaction writes a complete new copy of the live data into a generation
directory ``MAP/gen-N/`` (see :mod:`sprint_map.storage.generation`), renumbering the vertex ids
densely again so that "vertex = row" addressing and the tiling invariant hold without removed
ranges (sequence ids are stable; only vertex ids change):

1. ``gen-N/`` is created (a staging area: nothing selects it yet);
2. the live rows are copied, in vertex order, into ``gen-N/shards/`` (each shard fsynced);
3. every live record is written, renumbered, into a fresh LMDB environment ``gen-N/build.lmdb``
   in one transaction, which is then copied with ``env.copy(compact=True)`` into
   ``gen-N/map.lmdb`` (fsynced) and deleted;
4. the index is rebuilt from the new shards into ``gen-N/index/`` (published atomically; an
   approximate index is retrained on the renumbered vertices and its segments merged);
5. **commit point**: ``MAP/CURRENT`` is published atomically, naming ``gen-N``;
6. the writer switches to the new generation and deletes the old one, unless a reader still
   has it open (then the next writer's open deletes it, after that reader has closed).

A kill before step 5 leaves the old map selected and intact, plus an unselected ``gen-N`` that
the next writer's open removes; a kill after it leaves the new map selected and intact, plus the
old generation, removed the same way. The map is never in between: the one ``os.replace`` of
``CURRENT`` decides. Compaction runs under the writer lock (it is a writer's method).
"""

from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path
from typing import Protocol

import lmdb
import numpy as np

from sprint_map.errors import SprintMapError, StorageIOError
from sprint_map.storage.generation import (
    gen_name,
    gen_number,
    publish_current,
    remove_generation,
    stale_generations,
)
from sprint_map.storage.index.map_index import IndexStore
from sprint_map.storage.keys import u32, u64
from sprint_map.storage.lmdb_env import LmdbEnv
from sprint_map.storage.records import CompactReport, SequenceRecord
from sprint_map.storage.shards import ShardSet
from sprint_map.storage.store_config import SCHEMA_VERSION, StoreConfig
from sprint_map.testing.crash import crash_point
from sprint_map.util import atomic


class CompactableMap(Protocol):
    """What compaction uses of a map open for writing (``MapStore`` is one): its directory
    and live generation, records and shards to copy, a new index for the new generation, and
    the switch of the open map onto it."""

    @property
    def path(self) -> Path: ...

    @property
    def data_path(self) -> Path: ...

    @property
    def env(self) -> LmdbEnv: ...

    @property
    def shards(self) -> ShardSet: ...

    @property
    def index(self) -> IndexStore: ...

    @property
    def config(self) -> StoreConfig: ...

    @property
    def warnings(self) -> list[str]: ...

    @property
    def writing(self) -> object | None: ...

    def require_writer(self) -> None: ...

    def counter(self, name: str, txn: lmdb.Transaction | None = None) -> int: ...

    def disk_bytes(self) -> int: ...

    def new_index(self, directory: Path, *, writable: bool = True) -> IndexStore: ...

    def switch_generation(self, data: Path, index: IndexStore) -> None: ...


#: Rows copied per shard append, and LMDB records per bulk put.
COPY_ROWS = 65536
BATCH = 65536
#: Databases copied unchanged: keyed by sequence id, which compaction keeps.
SEQ_KEYED = ("seq_names", "uf", "members", "comp", "digests", "thumbnails", "sightings")
#: Databases whose keys are 1 or 2 big-endian vertex ids, renumbered on the way.
VERTEX_KEYED = {"vertex_data": 1, "edges": 2, "edges_rev": 2}


class Renumbering:
    """Old vertex id -> new vertex id of the live sequences, packed densely in vertex order."""

    def __init__(self, live: list[SequenceRecord]) -> None:
        self.live = sorted(live, key=lambda s: s.first_vertex)
        self.old_first = np.array([s.first_vertex for s in self.live], dtype=np.int64)
        self.old_last = np.array([s.last_vertex for s in self.live], dtype=np.int64)
        lengths = np.array([s.length for s in self.live], dtype=np.int64)
        self.new_first = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
        self.total = int(lengths.sum())

    def __call__(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(new ids, live mask)``; ids outside every live sequence are masked out."""
        at = np.searchsorted(self.old_first, ids, side="right") - 1
        safe = np.maximum(at, 0)
        live = (at >= 0) & (ids <= self.old_last[safe]) if len(self.live) else np.zeros(
            ids.shape, dtype=bool)
        if not len(self.live):
            return ids, live
        return ids - self.old_first[safe] + self.new_first[safe], live

    def record(self, seq: SequenceRecord) -> SequenceRecord:
        at = int(np.searchsorted(self.old_first, seq.first_vertex))
        return SequenceRecord(seq.seq_id, seq.name, seq.length, int(self.new_first[at]),
                              seq.created, seq.source)


def part_bytes(data: Path) -> dict[str, int]:
    """Allocated bytes of each part of the generation in ``data``."""
    out = {}
    for part in ("map.lmdb", "shards", "index"):
        total = 0
        for dirpath, _, files in os.walk(data / part):
            for name in files:
                with contextlib.suppress(FileNotFoundError):  # removed meanwhile
                    total += os.stat(os.path.join(dirpath, name)).st_blocks * 512
        out[part] = total
    return out


def compact_map(store: CompactableMap) -> CompactReport:
    """Write the live map into a new generation, select it atomically, drop the old one.

    Raises
    ------
    ReadOnlyMapError
        If ``store`` is not the writer.
    StorageIOError
        On an I/O error before the commit point (the old map stays selected, untouched; the
        staging directory is removed by the next writer's open) or after it (the new map is
        selected and complete; this ``store`` is unusable and must be reopened).

    Notes
    -----
    O(live vertices * dim) to copy the shards and rebuild the index, O(records) LMDB reads
    and bulk puts; peak disk use is the old map plus the new one.
    """
    store.require_writer()
    if store.writing is not None:
        raise SprintMapError("a sequence is being written: commit or abort it first")
    started = time.monotonic()
    root, old = store.path, store.data_path
    bytes_before, parts_before = store.disk_bytes(), part_bytes(old)
    for stale in stale_generations(root, old):  # leftovers of an interrupted compaction
        _remove_old(store, stale)
    new = root / gen_name(gen_number(root, old) + 1)
    try:
        if new.exists():  # a staging area a reader pinned? never: readers pin live ones only
            atomic.remove_tree(new)
        for part in (new, new / "shards", new / "index", new / "map.lmdb"):
            part.mkdir()
        atomic.fsync_dir(root)
    except OSError as exc:
        raise StorageIOError(f"cannot create {new}: {exc.strerror or exc}") from exc
    crash_point("compact.staging_created")

    with store.env.read() as txn:
        live = [SequenceRecord.decode(v) for _, v in txn.cursor(db=store.env.db("sequences"))]
        total = store.counter("next_vertex_id", txn)
    renumber = Renumbering(live)
    shards = ShardSet(new / "shards", store.config.dim, store.config.shard_rows)
    _copy_rows(store, shards, renumber, total)
    crash_point("compact.shards_written")

    _write_lmdb(store, new, renumber)
    crash_point("compact.lmdb_written")

    index = store.new_index(new / "index")
    try:
        index.adopt(store.index)  # the learned projection (descriptors, not ids: it carries over)
        index.rebuild(renumber.total, shards)
        index.merge_segments()  # an approximate index: its segments into one (else a no-op)
        atomic.fsync_dir(new)
    except OSError as exc:  # e.g. the directory fsync after removing older index files
        raise StorageIOError(f"cannot write the index of {new}: {exc.strerror or exc}") from exc
    crash_point("compact.before_publish")

    publish_current(root, new)  # the commit point
    crash_point("compact.published")
    store.switch_generation(new, index)
    removed = _remove_old(store, old)
    return CompactReport(
        generation=new.name,
        sequences=len(live),
        vertices_before=total,
        vertices_after=renumber.total,
        bytes_before=bytes_before,
        bytes_after=store.disk_bytes(),
        parts_before=parts_before,
        parts_after=part_bytes(new),
        old_generation_removed=removed,
        seconds=round(time.monotonic() - started, 3),
    )


def _remove_old(store: CompactableMap, data: Path) -> bool:
    """Delete a generation that is not live; an I/O error fails nothing (the next writer's
    open tries again): it goes to ``store.warnings``."""
    try:
        return remove_generation(store.path, data)
    except OSError as exc:
        store.warnings.append(f"could not remove {data.name or data}: {exc.strerror or exc}; "
                              "the next writer's open tries again")
        return False


def _copy_rows(store: CompactableMap, shards: ShardSet, renumber: Renumbering, total: int) -> None:
    """Append the live rows in vertex order, ``COPY_ROWS`` at a time (each append fsynced)."""
    pending: list[np.ndarray] = []
    held = written = 0
    for seq in renumber.live:
        for start in range(seq.first_vertex, seq.last_vertex + 1, COPY_ROWS):
            stop = min(seq.last_vertex + 1, start + COPY_ROWS)
            pending.append(store.shards.rows(start, stop, total))
            held += stop - start
            if held >= COPY_ROWS:
                shards.append(written, np.concatenate(pending))
                written += held
                pending, held = [], 0
    if held:
        shards.append(written, np.concatenate(pending))
    shards.close()


def _write_lmdb(store: CompactableMap, new: Path, renumber: Renumbering) -> None:
    """Write the renumbered records into ``new/build.lmdb``, copy it compacted into
    ``new/map.lmdb``, fsync the copy, delete the build environment."""
    build = new / "build.lmdb"
    build.mkdir()
    env = LmdbEnv(build, readonly=False, map_size=store.env.map_size(), create=True)
    try:
        env.write(lambda txn: _fill(store, env, txn, renumber))
        try:
            env.copy_compact(new / "map.lmdb")
        except lmdb.Error as exc:
            raise StorageIOError(f"cannot copy the compacted LMDB: {exc}") from exc
    finally:
        env.close()
    try:
        atomic.remove_tree(build)
        atomic.fsync_file(new / "map.lmdb" / "data.mdb")
        atomic.fsync_dir(new / "map.lmdb")
        atomic.fsync_dir(new)
    except OSError as exc:
        raise StorageIOError(f"cannot sync the compacted LMDB: {exc.strerror or exc}") from exc


def _fill(store: CompactableMap, env: LmdbEnv, out: lmdb.Transaction, renumber: Renumbering) -> None:
    """Every live record of ``store`` into ``out`` (an empty map's write txn), renumbered."""
    src = store.env
    with src.read() as txn:
        meta = env.db("meta")
        for key, value in txn.cursor(db=src.db("meta")):
            out.put(key, value, db=meta)
        out.put(b"next_vertex_id", u64(renumber.total), db=meta)
        out.put(b"removed_vertices", u64(0), db=meta)
        out.put(b"schema_version", str(SCHEMA_VERSION).encode(), db=meta)
        out.put(b"compacted", repr(time.time()).encode(), db=meta)
        by_id = sorted(renumber.live, key=lambda s: s.seq_id)
        out.cursor(db=env.db("sequences")).putmulti(
            ((u32(s.seq_id), renumber.record(s).encode()) for s in by_id), append=True)
        out.cursor(db=env.db("vrange")).putmulti(
            ((u64(renumber.record(s).last_vertex), u32(s.seq_id)) for s in renumber.live),
            append=True)
        for name in SEQ_KEYED:
            out.cursor(db=env.db(name)).putmulti(iter(txn.cursor(db=src.db(name))), append=True)
        lengths = store.shards.lengths_for(renumber.total)
        out.cursor(db=env.db("shards")).putmulti(
            ((u32(shard), u64(rows)) for shard, rows in sorted(lengths.items())), append=True)
        for name, fields in VERTEX_KEYED.items():
            _copy_renumbered(txn.cursor(db=src.db(name)), out.cursor(db=env.db(name)), fields,
                             renumber)


def _copy_renumbered(cursor: lmdb.Cursor, out: lmdb.Cursor, fields: int,
                     renumber: Renumbering) -> None:
    """Copy records keyed by ``fields`` big-endian u64 vertex ids, renumbering the ids and
    dropping records that touch no live vertex. Order-preserving: bulk puts in append mode."""
    keys: list[bytes] = []
    values: list[bytes] = []

    def flush() -> None:
        if not keys:
            return
        ids = np.frombuffer(b"".join(keys), dtype=">u8").astype(np.int64).reshape(-1, fields)
        new_ids, live = renumber(ids)
        keep = live.all(axis=1)
        packed = np.ascontiguousarray(new_ids[keep].astype(">u8")).tobytes()
        width = 8 * fields
        kept = [values[i] for i in np.flatnonzero(keep).tolist()]
        out.putmulti(((packed[i * width:(i + 1) * width], v) for i, v in enumerate(kept)),
                     append=True)
        keys.clear()
        values.clear()

    for key, value in cursor:
        keys.append(bytes(key))
        values.append(bytes(value))
        if len(keys) >= BATCH:
            flush()
    flush()


__all__ = ["CompactableMap", "Renumbering", "compact_map", "part_bytes"]
