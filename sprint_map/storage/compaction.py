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
from sprint_map.storage.keys import DIGEST_BYTES, u32, u64
from sprint_map.storage.lmdb_env import LmdbEnv
from sprint_map.storage.records import CompactReport, SequenceRecord
from sprint_map.storage.reduction import (
    Reduction,
    reduced_edges,
    reduced_sightings,
    reduced_thumbnails,
    regroup_all,
)
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
SEQ_KEYED = ("seq_names", "uf", "members", "comp", "digests", "thumbnails", "sightings",
             "drive_stats")
#: Databases whose keys are 1 or 2 big-endian vertex ids, renumbered on the way.
VERTEX_KEYED = {"vertex_data": 1, "edges": 2, "edges_rev": 2}


class Renumbering:
    """Old vertex id -> new vertex id of the live sequences, packed densely in vertex order.

    With ``keep`` (bool per old vertex id: a summary's :class:`Reduction`) only the kept
    vertices are numbered, a sequence's image ids become its kept frames in order, and a
    sequence that keeps none is left out (:attr:`gone`)."""

    def __init__(self, live: list[SequenceRecord], keep: np.ndarray | None = None) -> None:
        ordered = sorted(live, key=lambda s: s.first_vertex)
        self.keep = keep
        if keep is None:
            kept = [s.length for s in ordered]
        else:
            kept = [int(keep[s.first_vertex:s.last_vertex + 1].sum()) for s in ordered]
        #: sequences that keep no frame (a summary drops them whole)
        self.gone = [s for s, n in zip(ordered, kept, strict=True) if n == 0]
        self.live = [s for s, n in zip(ordered, kept, strict=True) if n > 0]
        self.old_first = np.array([s.first_vertex for s in self.live], dtype=np.int64)
        self.old_last = np.array([s.last_vertex for s in self.live], dtype=np.int64)
        lengths = np.array([n for n in kept if n > 0], dtype=np.int64)
        self.lengths = lengths
        self.new_first = (np.cumsum(lengths) - lengths).astype(np.int64)  # [] when none is kept
        self.total = int(lengths.sum())
        self._dense: np.ndarray | None = None
        if keep is not None:  # old id -> new id, -1 where dropped or in no live sequence
            dense = np.full(len(keep), -1, dtype=np.int64)
            for s, first in zip(self.live, self.new_first.tolist(), strict=True):
                mask = keep[s.first_vertex:s.last_vertex + 1]
                dense[s.first_vertex + np.flatnonzero(mask)] = first + np.arange(mask.sum())
            self._dense = dense

    def __call__(self, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(new ids, live mask)``; ids outside every live sequence (or dropped) are masked
        out."""
        if self._dense is not None:
            inside = (ids >= 0) & (ids < len(self._dense))
            new = np.where(inside, self._dense[np.where(inside, ids, 0)], -1)
            return new, new >= 0
        at = np.searchsorted(self.old_first, ids, side="right") - 1
        safe = np.maximum(at, 0)
        live = (at >= 0) & (ids <= self.old_last[safe]) if len(self.live) else np.zeros(
            ids.shape, dtype=bool)
        if not len(self.live):
            return ids, live
        return ids - self.old_first[safe] + self.new_first[safe], live

    def record(self, seq: SequenceRecord) -> SequenceRecord:
        at = int(np.searchsorted(self.old_first, seq.first_vertex))
        return SequenceRecord(seq.seq_id, seq.name, int(self.lengths[at]),
                              int(self.new_first[at]), seq.created, seq.source)

    def image_map(self, seq: SequenceRecord) -> np.ndarray:
        """Old image id -> new image id of ``seq`` (-1 where dropped)."""
        if self.keep is None:
            return np.arange(seq.length, dtype=np.int64)
        mask = self.keep[seq.first_vertex:seq.last_vertex + 1]
        out = np.full(seq.length, -1, dtype=np.int64)
        out[mask] = np.arange(int(mask.sum()))
        return out


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


def compact_map(store: CompactableMap, reduction: Reduction | None = None) -> CompactReport:
    """Write the live map into a new generation, select it atomically, drop the old one.

    With ``reduction`` (``summarize``: :mod:`sprint_map.storage.reduction`) the new generation
    holds only the kept vertices, with the edges, sightings and components the reduction
    makes; its crash points are named ``summarize.*`` instead of ``compact.*``.

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
    summary = reduction is not None
    if reduction is not None:  # (before anything is written)
        reduction.validate(store.counter("next_vertex_id"))
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
    if summary:
        crash_point("summarize.staging_created")
    else:
        crash_point("compact.staging_created")

    with store.env.read() as txn:
        live = [SequenceRecord.decode(v) for _, v in txn.cursor(db=store.env.db("sequences"))]
        total = store.counter("next_vertex_id", txn)
    renumber = Renumbering(live, None if reduction is None else reduction.keep)
    shards = ShardSet(new / "shards", store.config.dim, store.config.shard_rows)
    digests = _copy_rows(store, shards, renumber, total)
    if summary:
        crash_point("summarize.shards_written")
    else:
        crash_point("compact.shards_written")

    _write_lmdb(store, new, renumber, reduction, digests)
    if summary:
        crash_point("summarize.lmdb_written")
    else:
        crash_point("compact.lmdb_written")

    index = store.new_index(new / "index")
    try:
        index.adopt(store.index)  # the learned projection (descriptors, not ids: it carries over)
        index.rebuild(renumber.total, shards)
        index.merge_segments()  # an approximate index: its segments into one (else a no-op)
        atomic.fsync_dir(new)
    except OSError as exc:  # e.g. the directory fsync after removing older index files
        raise StorageIOError(f"cannot write the index of {new}: {exc.strerror or exc}") from exc
    if summary:
        crash_point("summarize.before_publish")
    else:
        crash_point("compact.before_publish")

    publish_current(root, new)  # the commit point
    if summary:
        crash_point("summarize.published")
    else:
        crash_point("compact.published")
    store.switch_generation(new, index)
    removed = _remove_old(store, old)
    return CompactReport(
        generation=new.name,
        sequences=len(renumber.live),
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


def _copy_rows(store: CompactableMap, shards: ShardSet, renumber: Renumbering, total: int
               ) -> dict[int, bytes]:
    """Append the live (kept) rows in vertex order, ``COPY_ROWS`` at a time (each append
    fsynced). Returns the new digest of each sequence a reduction shortened."""
    import hashlib  # (here: commands that only read a map never load OpenSSL)

    pending: list[np.ndarray] = []
    held = written = 0
    digests: dict[int, bytes] = {}
    for seq in renumber.live:
        mask = (None if renumber.keep is None
                else renumber.keep[seq.first_vertex:seq.last_vertex + 1])
        shortened = mask is not None and not mask.all()
        digest = hashlib.blake2b(digest_size=DIGEST_BYTES)
        for start in range(seq.first_vertex, seq.last_vertex + 1, COPY_ROWS):
            stop = min(seq.last_vertex + 1, start + COPY_ROWS)
            rows = store.shards.rows(start, stop, total)
            if shortened:
                assert mask is not None
                rows = rows[mask[start - seq.first_vertex:stop - seq.first_vertex]]
                digest.update(np.ascontiguousarray(rows, dtype="<f4").data)
            pending.append(rows)
            held += len(rows)
            if held >= COPY_ROWS:
                shards.append(written, np.concatenate(pending))
                written += held
                pending, held = [], 0
        if shortened:
            digests[seq.seq_id] = digest.digest()
    if held:
        shards.append(written, np.concatenate(pending))
    shards.close()
    return digests


def _write_lmdb(store: CompactableMap, new: Path, renumber: Renumbering,
                reduction: Reduction | None = None, digests: dict[int, bytes] | None = None
                ) -> None:
    """Write the renumbered records into ``new/build.lmdb``, copy it compacted into
    ``new/map.lmdb``, fsync the copy, delete the build environment."""
    build = new / "build.lmdb"
    build.mkdir()
    env = LmdbEnv(build, readonly=False, map_size=store.env.map_size(), create=True)
    try:
        if reduction is None:
            env.write(lambda txn: _fill(store, env, txn, renumber))
        else:
            env.write(lambda txn: _fill_reduced(store, env, txn, renumber, reduction,
                                                digests or {}))
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


def _fill_reduced(store: CompactableMap, env: LmdbEnv, out: lmdb.Transaction,
                  renumber: Renumbering, reduction: Reduction, digests: dict[int, bytes]
                  ) -> None:
    """:func:`_fill` for a summary: the kept vertices, their sequences shortened, the edges
    moved off dropped vertices (:mod:`sprint_map.storage.reduction`), sightings folded and
    counted, components regrouped, counters recounted."""
    src = store.env
    records = [renumber.record(s) for s in renumber.live]
    old_by_id = {s.seq_id: s for s in renumber.live + renumber.gone}
    gone = {s.seq_id for s in renumber.gone}
    maps = {s.seq_id: renumber.image_map(s) for s in renumber.live}
    starts = np.array([s.first_vertex for s in renumber.live], dtype=np.int64)

    def span_of(seq: int) -> tuple[int, int] | None:
        rec = old_by_id.get(seq)
        return None if rec is None else (rec.first_vertex, rec.length)

    def locate(vertex: int) -> tuple[int, int]:
        seq = renumber.live[int(np.searchsorted(starts, vertex, side="right")) - 1]
        return seq.seq_id, vertex - seq.first_vertex

    with src.read() as txn:
        meta = env.db("meta")
        for key, value in txn.cursor(db=src.db("meta")):
            out.put(key, value, db=meta)
        edges = reduced_edges(txn, src, renumber,
                              np.array([r.first_vertex for r in records], dtype=np.int64),
                              reduction)
        out.put(b"next_vertex_id", u64(renumber.total), db=meta)
        out.put(b"removed_vertices", u64(0), db=meta)
        out.put(b"schema_version", str(SCHEMA_VERSION).encode(), db=meta)
        out.put(b"compacted", repr(time.time()).encode(), db=meta)
        out.put(b"n_sequences", u64(len(records)), db=meta)
        out.put(b"n_edges", u64(len(edges)), db=meta)
        out.cursor(db=env.db("sequences")).putmulti(
            ((u32(r.seq_id), r.encode()) for r in sorted(records, key=lambda r: r.seq_id)),
            append=True)
        out.cursor(db=env.db("vrange")).putmulti(
            ((u64(r.last_vertex), u32(r.seq_id)) for r in records), append=True)
        out.cursor(db=env.db("seq_names")).putmulti(
            (k, v) for k, v in txn.cursor(db=src.db("seq_names"))
            if int.from_bytes(v, "big") not in gone)
        out.cursor(db=env.db("digests")).putmulti(
            ((k, digests.get(int.from_bytes(k, "big"), bytes(v)))
             for k, v in txn.cursor(db=src.db("digests"))
             if int.from_bytes(k, "big") not in gone), append=True)
        if src.has_db("drive_stats"):  # a summary keeps the drive's statistics as driven
            out.cursor(db=env.db("drive_stats")).putmulti(
                ((k, v) for k, v in txn.cursor(db=src.db("drive_stats"))
                 if int.from_bytes(k, "big") not in gone), append=True)
        if src.has_db("thumbnails"):
            out.cursor(db=env.db("thumbnails")).putmulti(
                reduced_thumbnails(txn, src.db("thumbnails"), maps.get), append=True)
        out.cursor(db=env.db("sightings")).putmulti(
            reduced_sightings(txn, src, reduction, locate, maps.__getitem__, span_of),
            append=True)
        lengths = store.shards.lengths_for(renumber.total)
        out.cursor(db=env.db("shards")).putmulti(
            ((u32(shard), u64(rows)) for shard, rows in sorted(lengths.items())), append=True)
        _copy_renumbered(txn.cursor(db=src.db("vertex_data")),
                         out.cursor(db=env.db("vertex_data")), 1, renumber)
        out.cursor(db=env.db("edges")).putmulti(edges, append=True)
        out.cursor(db=env.db("edges_rev")).putmulti(
            sorted((k[8:] + k[:8], b"") for k, _ in edges), append=True)
        out.put(b"n_components", u64(regroup_all(out, env, records, edges)), db=meta)


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
