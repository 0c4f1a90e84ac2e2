"""MapStore: the persistent map directory (LMDB + descriptor shards + FAISS index).

The store knows sequences, vertices, edges, components and descriptors; it knows nothing of HMMs.

Commit protocol for :meth:`MapStore.add_sequence` (see ``docs/architecture.md``):

1. validate everything (nothing is written for bad input);
2. append the descriptor rows to the shards and fsync them (invisible: LMDB does not count them);
3. one LMDB write transaction records the sequence, its vertex range, per-vertex data, edges,
   union-find merges, shard lengths and counters: **the commit point**;
4. add the rows to the in-memory index (if loaded); persist it every ``index_persist_every``
   vertices and on close.

A kill before 3 leaves bytes past the committed shard length, truncated on the next writable
open; a kill after 3 leaves an index that lags LMDB, caught up from the shards on load.
"""

from __future__ import annotations

import contextlib
import json
import os
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import AbstractContextManager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import lmdb
import numpy as np

from sprint_map.errors import (
    MapCorruptError,
    MapExistsError,
    NotAMapError,
    ReadOnlyMapError,
    SchemaVersionError,
    SprintMapError,
    StorageIOError,
)
from sprint_map.storage import learning
from sprint_map.storage.components import ComponentStore
from sprint_map.storage.generation import (
    current_data,
    pin_current,
    remove_generation,
    stale_generations,
    unpin,
)
from sprint_map.storage.group_writer import GroupWriter
from sprint_map.storage.index.map_index import IndexStore
from sprint_map.storage.index.projection import LearnReport
from sprint_map.storage.keys import (
    decode_json,
    decode_number,
    read_u64,
    u32,
    u64,
)
from sprint_map.storage.lmdb_env import LmdbEnv
from sprint_map.storage.lock import WriterLock
from sprint_map.storage.provenance import unmerge_sequence
from sprint_map.storage.records import (
    AddResult,
    CompactReport,
    EdgeSpec,
    RemoveResult,
    SequenceRecord,
    UnmergeResult,
)
from sprint_map.storage.removal import RemovedRanges, remove_sequences, search_live
from sprint_map.storage.sequence_writer import SequenceWriter, record_live_sightings
from sprint_map.storage.shards import ShardSet
from sprint_map.storage.store_config import (
    READABLE_SCHEMA_VERSIONS,
    SCHEMA_VERSION,
    ConfigRecord,
    StoreConfig,
    decode_stored_config,
)
from sprint_map.storage.store_reads import StoreReads
from sprint_map.testing.crash import crash_point
from sprint_map.util.arrays import Descriptors, DescriptorsLike, SearchResult
from sprint_map.util.atomic import fsync_dir, remove_partials
from sprint_map.util.validation import decode_text, validate_descriptors

if TYPE_CHECKING:  # compaction loads when a map is compacted, not when one is opened
    from sprint_map.storage.reduction import Reduction

LMDB_DIR = "map.lmdb"
SHARDS_DIR = "shards"
INDEX_DIR = "index"
COUNTERS = ("next_seq_id", "next_vertex_id", "n_sequences", "n_edges", "n_components")


class MapStore(StoreReads):
    """A map directory opened for reading, or for writing by this process alone.

    Use :meth:`create` or :meth:`open`; close with :meth:`close` or a ``with`` block. What it
    reads of the committed map (sequences, vertices, positions, thumbnails, sightings,
    components, edges) is :class:`~sprint_map.storage.store_reads.StoreReads`'.

    Notes
    -----
    Opening reads the meta record and, for a writer, truncates the one open shard: O(1) in the
    number of vertices, edges and shards. Nothing else is loaded until asked for.
    """

    def __init__(self, path: Path, env: LmdbEnv, lock: WriterLock | None, readonly: bool,
                 data: Path | None = None) -> None:
        self.path = path
        #: The live generation's directory (``path`` itself until the first compaction).
        self.data_path = path if data is None else data
        self.env = env
        self._lock = lock
        self._pin: int | None = None  # shared flock on the generation (see storage/generation)
        self.readonly = readonly
        with env.read() as txn:
            meta = env.db("meta")
            raw_version = txn.get(b"schema_version", db=meta)
            if raw_version is None:
                raise NotAMapError(f"not a sprint-map directory (no schema version): {path}")
            version = decode_number(raw_version, "schema_version")
            if version not in READABLE_SCHEMA_VERSIONS:
                raise SchemaVersionError(
                    f"map schema version {version} is not supported by this sprint-map "
                    f"(it reads version {SCHEMA_VERSION} and older)"
                    f"{'; upgrade sprint-map' if version > SCHEMA_VERSION else ''}"
                )
            self.schema_version = version
            raw_config = txn.get(b"config", db=meta)
            if raw_config is None:
                raise MapCorruptError(f"map has no config record: {path}")
            #: The whole configuration as stored (the facade decodes what is not storage's).
            self.config_record = decode_json(raw_config, "config")
            #: The storage layer's fields of it.
            self.config = decode_config(self.config_record)
            raw_created = txn.get(b"created", db=meta)
            self.created = 0.0 if raw_created is None else decode_number(raw_created, "created",
                                                                         float)
        self.uf = ComponentStore(env)
        self.shards = ShardSet(self.data_path / SHARDS_DIR, self.config.dim,
                               self.config.shard_rows)
        self.index = self.new_index(self.data_path / INDEX_DIR, writable=not readonly)
        self._removed: tuple[int, RemovedRanges] | None = None  # cache, by removed_vertices
        self.recovery: list[str] = []
        #: Problems that lost nothing and failed no operation (e.g. the index cache not saved).
        self.warnings: list[str] = []
        self._writing: SequenceWriter | GroupWriter | None = None
        self._grouped = 0  # depth of group_commit blocks
        self._persist_due = False  # an index persist deferred to the end of the group

    # --- lifecycle --------------------------------------------------------------------------
    @classmethod
    def create(cls, path: str | os.PathLike[str], config: ConfigRecord) -> MapStore:
        """Create a new, empty map at ``path`` (absent or an empty directory) and open it.

        ``config`` (a ``MapConfig``) is stored as the JSON object its ``to_dict`` gives; the
        store reads its own fields of it (:class:`StoreConfig`). A ``path`` that is not UTF-8
        text is refused (InputError) before anything is made.
        """
        record = config.to_dict()
        settings = StoreConfig.from_record(record)
        root = Path(decode_text(os.fspath(path), "map path"))
        if root.exists() and (not root.is_dir() or any(root.iterdir())):
            raise MapExistsError(f"refusing to create a map in non-empty path: {root}")
        created: list[Path] = []  # what this call made, undone (newest first) on failure
        lock = WriterLock(root)
        env = None
        try:
            for parent in reversed(root.parents):
                if not parent.exists():
                    parent.mkdir()
                    created.append(parent)
            if not root.exists():
                root.mkdir()
                created.append(root)
            for sub in (SHARDS_DIR, INDEX_DIR, LMDB_DIR):
                (root / sub).mkdir()
                created.append(root / sub)
            created.append(lock.path)
            lock.acquire()
            env = LmdbEnv(root / LMDB_DIR, readonly=False, map_size=settings.initial_map_size,
                          create=True)

            def body(txn: lmdb.Transaction) -> None:
                meta = env.db("meta")
                # The schema version is written last in the same transaction: a directory
                # without it is "not a map", never a half map.
                for name in COUNTERS:
                    txn.put(name.encode(), u64(0), db=meta)
                txn.put(b"config", json.dumps(record).encode(), db=meta)
                txn.put(b"created", repr(time.time()).encode(), db=meta)
                txn.put(b"schema_version", str(SCHEMA_VERSION).encode(), db=meta)

            env.write(body)
            fsync_dir(root)
            store = cls(root, env, lock, readonly=False)
            store._pin = pin_current(root)[1]
            return store
        except BaseException:
            if env is not None:
                env.close()
            lock.release()
            _undo_create(created)
            raise

    @classmethod
    def open(cls, path: str | os.PathLike[str], *, readonly: bool = False,
             check_config: Callable[[dict[str, Any]], object] | None = None) -> MapStore:
        """Open an existing map. A writer takes the map's lock and recovers interrupted writes.

        ``check_config``, if given, is called with the stored configuration record
        (:attr:`config_record`) before a writer changes anything; whatever it raises fails the
        open (the facade checks the fields that are not storage's). A ``path`` that is not
        UTF-8 text is refused (InputError).
        """
        root = Path(decode_text(os.fspath(path), "map path"))
        if not root.is_dir() or not (current_data(root) / LMDB_DIR / "data.mdb").is_file():
            raise NotAMapError(f"not a sprint-map directory: {root}")
        lock = None
        if not readonly:
            data = current_data(root)
            for part in (root, data, data / LMDB_DIR, data / LMDB_DIR / "data.mdb",
                         data / SHARDS_DIR, data / INDEX_DIR):
                if part.exists() and not os.access(part, os.W_OK):
                    raise ReadOnlyMapError(f"map is not writable ({part}); it can only be read")
            lock = WriterLock(root)
            lock.acquire()
        env = None
        pin = None
        try:
            # Under the writer lock no compaction can switch generations; a reader's pin keeps
            # the generation it opened in place for as long as it stays open.
            data, pin = pin_current(root)
            if pin is None:
                raise NotAMapError(f"not a sprint-map directory: {root}")
            env = LmdbEnv(data / LMDB_DIR, readonly=readonly, map_root=root)
            store = cls(root, env, lock, readonly, data)
            store._pin = pin
            if check_config is not None:
                check_config(store.config_record)
        except BaseException:
            # py-lmdb refuses a second open of an environment that is still open in this
            # process, so a refused open (e.g. SchemaVersionError) must not leave it open.
            if env is not None:
                env.close()
            unpin(pin)
            if lock is not None:
                lock.release()
            raise
        if not readonly:
            try:
                store._recover()
            except BaseException:  # e.g. an I/O error: release the map, as a failed open must
                env.close()
                unpin(pin)
                if lock is not None:
                    lock.release()
                raise
        return store

    def new_index(self, directory: Path, *, writable: bool = True) -> IndexStore:
        """The index of this map's config kept in ``directory`` (also a compaction's staging)."""
        return IndexStore(directory, self.config.dim, writable=writable, config=self.config)

    def switch_generation(self, data: Path, index: IndexStore) -> None:
        """Reopen this writer on the just-published generation ``data`` with its ``index``.

        The old generation's environment is closed and its pin dropped first, so that the
        caller can remove it. A failure leaves this store closed (the map itself is complete).
        """
        self.index.close()  # a segment sealing in flight writes into the old generation
        self.shards.close()
        self.env.close()
        unpin(self._pin)
        self._pin = None
        self.env = None  # type: ignore[assignment]
        try:
            pinned, pin = pin_current(self.path)
            self._pin = pin
            if pinned != data or pin is None:
                raise MapCorruptError(f"the map's live generation is {pinned}, not {data}")
            self.env = LmdbEnv(data / LMDB_DIR, readonly=False)
        except BaseException:
            unpin(self._pin)
            self._pin = None
            if self._lock is not None:
                self._lock.release()
            raise
        self.data_path = data
        self.uf = ComponentStore(self.env)
        self.shards = ShardSet(data / SHARDS_DIR, self.config.dim, self.config.shard_rows)
        self.index = index
        self._removed = None

    def _recover(self) -> None:
        """Bring files back to the committed state (writer only). O(1) in the map size but
        for one ``stat`` per shard file (:meth:`ShardSet.verify`): a map whose shards lost
        committed rows is refused (MapCorruptError), never refilled.

        Also migrates a schema-1 map to schema 2 (the version record only: every schema-1 map
        is a schema-2 map without removed ranges; the ``removed`` database was created by the
        environment's open) and removes the generations a compaction left behind, unless a
        reader still has one open.
        """
        if self.schema_version < SCHEMA_VERSION:
            self.env.write(lambda txn: txn.put(b"schema_version", str(SCHEMA_VERSION).encode(),
                                               db=self.env.db("meta")))
            self.recovery.append(f"upgraded the map from schema version {self.schema_version} "
                                 f"to {SCHEMA_VERSION}")
            self.schema_version = SCHEMA_VERSION
        for stale in stale_generations(self.path, self.data_path):
            name = "generation 0 (top level)" if stale == self.path else stale.name
            try:  # never read again: a failure to delete it must not fail the open
                if remove_generation(self.path, stale):
                    self.recovery.append(f"removed {name}, no longer the live generation")
            except OSError as exc:
                self.warnings.append(f"could not remove {name} ({exc.strerror or exc}); the "
                                     "next writer's open tries again")
        for directory in dict.fromkeys((self.path, self.data_path, self.data_path / SHARDS_DIR,
                                        self.data_path / INDEX_DIR)):
            for removed in remove_partials(directory):
                self.recovery.append(f"removed leftover temp file {removed.name}")
        crash_point("recover.partials_removed")
        committed = self.counter("next_vertex_id")
        self.shards.verify(committed)  # a writer never fills lost committed rows with zeros
        self.recovery.extend(self.shards.recover(committed))
        crash_point("recover.shards_truncated")
        self.recovery.extend(self.index.discard_untrusted(committed))

    def close(self) -> None:
        """Persist the index (writer) and release everything. Idempotent."""
        if self.env is None:
            return
        try:
            if not self.readonly:
                try:
                    self.flush()
                except Exception as exc:  # a cache of committed data: nothing is lost
                    self.warnings.append(f"index cache not saved ({exc}); rebuilt when needed")
        finally:
            self.shards.close()
            self.env.close()
            self.env = None  # type: ignore[assignment]
            unpin(self._pin)
            self._pin = None
            if self._lock is not None:
                self._lock.release()

    def flush(self) -> None:
        """Persist the in-memory index if it covers vertices the file on disk does not.

        Raises
        ------
        StorageIOError
            If the index file cannot be written; the committed map is untouched.
        """
        self.require_writer()
        try:
            self.index.persist()
        except OSError as exc:  # e.g. the directory fsync after removing older index files
            raise StorageIOError(f"cannot save the index in {self.data_path / INDEX_DIR}: "
                                 f"{exc.strerror or exc}") from exc

    def __enter__(self) -> MapStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def require_writer(self) -> None:
        """Raise ``ReadOnlyMapError`` unless this store was opened for writing."""
        if self.readonly:
            raise ReadOnlyMapError("the map is open read-only")

    @property
    def writer_lock(self) -> WriterLock | None:
        """The map's writer lock this store holds (``None`` when read-only)."""
        return self._lock

    @property
    def writing(self) -> SequenceWriter | GroupWriter | None:
        """The sequence (or group of sequences) being written, if any (one at a time per
        writer)."""
        return self._writing

    def start_writing(self, writer: object) -> None:
        """Record ``writer`` (a :class:`SequenceWriter` or a :class:`GroupWriter`) as the one
        write in progress (each calls it once it has checked its name). Raises SprintMapError
        if another one is."""
        self.require_writer()
        if self._writing is not None:
            raise SprintMapError("another sequence is already being written to this map")
        assert isinstance(writer, SequenceWriter | GroupWriter)
        self._writing = writer

    def end_writing(self, writer: object) -> None:
        """``writer`` committed or aborted: another sequence may be written."""
        if self._writing is writer:
            self._writing = None

    # --- meta -------------------------------------------------------------------------------
    def stats(self) -> dict[str, int]:
        """Counts of the map from its meta record. O(1)."""
        with self.env.read() as txn:
            counts = {name: self.counter(name, txn) for name in COUNTERS}
        return {
            "sequences": counts["n_sequences"],
            "vertices": counts["next_vertex_id"],
            "edges": counts["n_edges"],
            "components": counts["n_components"],
        }

    def disk_bytes(self) -> int:
        """Bytes used by the map directory (actual allocation, LMDB files are sparse)."""
        total = 0
        for dirpath, _, files in os.walk(self.path):
            for name in files:
                with contextlib.suppress(FileNotFoundError):  # removed by a writer meanwhile
                    total += os.stat(os.path.join(dirpath, name)).st_blocks * 512
        return total

    # --- small writes -----------------------------------------------------------------------
    def set_geo_frame(self, record: dict[str, Any]) -> dict[str, Any]:
        """Store ``record`` as the map's geographic frame unless it has one; return the one
        it keeps (set once, never replaced). One small LMDB transaction. O(1)."""
        self.require_writer()
        meta = self.env.db("meta")

        def body(txn: lmdb.Transaction) -> dict[str, Any]:
            raw = txn.get(b"geo_frame", db=meta)
            if raw is not None:
                kept = decode_json(raw, "geo_frame")
                if not isinstance(kept, dict):
                    raise MapCorruptError("corrupt geo_frame record: not a JSON object")
                return kept
            txn.put(b"geo_frame", json.dumps(record).encode(), db=meta)
            return record

        result: dict[str, Any] = self.env.write(body)
        return result

    def record_sightings(self, drive: str, sightings: Sequence[tuple[int, int, float]]) -> int:
        """Commit, alone, the sightings of a drive that stored no frame: ``(seq_id, image_id,
        distance)`` per redundant frame (:mod:`sprint_map.storage.sightings`; those of vertices
        no longer in the map are dropped). Returns how many were counted. One LMDB
        transaction, O(m log n)."""
        self.require_writer()
        if self._writing is not None:
            raise SprintMapError("a sequence is being written: commit or abort it first")

        def body(txn: lmdb.Transaction) -> int:
            counted = record_live_sightings(self, txn, sightings, drive)
            crash_point("sightings.before_commit")
            return counted

        counted: int = self.env.write(body)
        crash_point("sightings.committed")
        return counted

    # --- retrieval ---------------------------------------------------------------------------
    def search(self, queries: DescriptorsLike, k: int) -> SearchResult:
        """k-NN over every live descriptor: ``(squared L2 distances, vertex ids)``, -1 padded.

        Hits in the vertex ranges of removed sequences (still in the shards and the index until
        ``compact``) are filtered out; the index is asked for more candidates until each query
        has ``k`` live hits or the index has no more (see :func:`removal.search_live`).
        """
        queries = validate_descriptors(queries, self.config.dim)
        total, removed = self._searchable()
        if not removed.count:
            return self.index.search(queries, k)
        return search_live(self.index.search, queries, k, removed, total)

    def _searchable(self) -> tuple[int, RemovedRanges]:
        """The committed vertices and removed ranges of one snapshot, the index loaded to
        them (what every search starts with). O(removed) plus the index's catch-up."""
        with self.env.read() as txn:
            total = self.counter("next_vertex_id", txn)
            removed = self.removed_ranges(txn)
        self.index.load(total, self.shards)
        return total, removed

    def search_within(self, queries: DescriptorsLike, k: int, start: int, stop: int | None
                      ) -> SearchResult:
        """:meth:`search` among the live vertex ids ``[start, stop)`` only (``stop`` None: to
        the last committed), on the approximate index (ValueError while it is exact).

        Notes
        -----
        The approximate index's search over the segments holding ids of the range
        (:meth:`IndexStore.search_within
        <sprint_map.storage.index.map_index.IndexStore.search_within>`).
        """
        queries = validate_descriptors(queries, self.config.dim)
        total, removed = self._searchable()
        end = total if stop is None else min(stop, total)

        def within(q: Descriptors, n: int) -> SearchResult:
            return self.index.search_within(q, n, start, max(start, end))

        if not removed.count:
            return within(queries, k)
        return search_live(within, queries, k, removed, total)

    def index_segments(self) -> list[tuple[int, int]]:
        """The vertex ranges ``(start, stop)`` of the approximate index's sealed segments, in
        order (none while the index is exact). O(segments) once the index is loaded."""
        self._searchable()
        return self.index.segment_bounds()

    def rebuild_index(self, *, train: bool = False) -> list[str]:
        """Rebuild (flat) or retrain and re-encode (approximate) the index; publish it
        atomically. O(vertices * dim) plus training."""
        self.require_writer()
        total = self.counter("next_vertex_id")
        try:
            if train:
                return self.index.train(total, self.shards)
            self.index.rebuild(total, self.shards)
        except OSError as exc:
            raise StorageIOError(f"cannot write the index in {self.data_path / INDEX_DIR}: "
                                 f"{exc.strerror or exc}") from exc
        return [f"rebuilt the index from the shards ({total} vertices): "
                f"{self.index.describe()['type']}"]

    def defer_index_retraining(self) -> None:
        """Stop retraining the approximate index inside commits (``index_retrain_growth``):
        :meth:`retrain_index_beside` does it instead, between commits. O(1)."""
        self.index.defer_retrain = True

    def retrain_index_beside(self, exclusive: Callable[[], AbstractContextManager[object]]
                             ) -> bool:
        """Retrain the approximate index if the map outgrew it (``index_retrain_growth``)
        while searches go on, switching under ``exclusive()``
        (:meth:`IndexStore.retrain_beside
        <sprint_map.storage.index.map_index.IndexStore.retrain_beside>`); True if it did."""
        self.require_writer()
        return self.index.retrain_beside(self.counter("next_vertex_id"), self.shards, exclusive)

    # --- removal ----------------------------------------------------------------------------
    def removed_vertices(self, txn: lmdb.Transaction | None = None) -> int:
        """Vertices of removed sequences not yet reclaimed by ``compact``. O(1)."""
        if txn is None:
            with self.env.read() as txn:
                return self.removed_vertices(txn)
        raw = txn.get(b"removed_vertices", db=self.env.db("meta"))
        return 0 if raw is None else read_u64(raw)

    def removed_ranges(self, txn: lmdb.Transaction) -> RemovedRanges:
        """The removed vertex ranges as of ``txn`` (cached until the next removal).

        Notes
        -----
        O(1) when cached (one meta read), else O(removed sequences) to read them.
        """
        count = self.removed_vertices(txn)
        if self._removed is None or self._removed[0] != count:
            self._removed = (count, RemovedRanges.read(self.env, txn))
        return self._removed[1]

    def compact(self) -> CompactReport:
        """Reclaim removed sequences' space: see :func:`compaction.compact_map`."""
        from sprint_map.storage.compaction import compact_map

        return compact_map(self)

    def summarize(self, reduction: Reduction) -> CompactReport:
        """Write the map without the vertices ``reduction`` drops, as a new generation selected
        atomically: see :mod:`reduction` and :func:`compaction.compact_map`."""
        from sprint_map.storage.compaction import compact_map

        return compact_map(self, reduction)

    def remove_sequences(self, seq_ids: Iterable[int]) -> RemoveResult:
        """Retire sequences in one LMDB transaction; see :func:`removal.remove_sequences`."""
        self.require_writer()
        if self._writing is not None:
            raise SprintMapError("a sequence is being written: commit or abort it first")
        return remove_sequences(self, seq_ids)

    def unmerge(self, seq_id: int) -> UnmergeResult:
        """Revoke the edges sequence ``seq_id`` added, in one LMDB transaction; see
        :func:`provenance.unmerge_sequence`."""
        self.require_writer()
        if self._writing is not None:
            raise SprintMapError("a sequence is being written: commit or abort it first")
        return unmerge_sequence(self, seq_id)

    # --- writing ----------------------------------------------------------------------------
    def add_sequence(
        self,
        descriptors: Any,
        *,
        name: str | None = None,
        positions: np.ndarray | None = None,
        edges: Sequence[EdgeSpec] = (),
        source: str = "",
        thumbnails: Sequence[bytes] | None = None,
        stats: tuple[int, np.ndarray] | None = None,
    ) -> AddResult:
        """Append a sequence, its vertices and edges in one atomic commit.

        Parameters
        ----------
        descriptors : array_like, shape (N, dim)
            One descriptor per frame (converted to float32; NaN/Inf refused).
        name : str, optional
            Unique sequence name (default ``seq-<id>``). Names are unique within a map.
        positions : array_like, shape (N, 2..4), optional
            Per-frame ``x, y[, heading_deg[, timestamp]]``.
        edges : sequence of EdgeSpec
            Inter-sequence edges to commit with it; their sequences' components are merged.
        source : str
            Free text recording where the sequence came from.
        thumbnails : sequence of bytes, optional
            One small JPEG per frame, committed with it (:mod:`~sprint_map.storage.thumbnails`).
        stats : (int, array_like), optional
            The drive's frames and mean descriptor, committed with it
            (:mod:`~sprint_map.storage.drive_stats`).

        Notes
        -----
        O(N * dim) shard I/O + O(N) LMDB puts + O(E log n) for edges and unions.
        """
        rows = validate_descriptors(descriptors, self.config.dim)
        with SequenceWriter(self, name, source) as writer:
            # Everything is validated before the first row is written.
            writer.prepare(positions, edges, len(rows))
            if stats is not None:
                writer.set_stats(*stats)
            writer.append(rows)
            return writer.commit(positions, edges, thumbnails)

    def begin_sequence(self, name: str | None = None, source: str = "") -> SequenceWriter:
        """Start streaming a new sequence: ``append`` batches, then ``commit`` (atomic)."""
        return SequenceWriter(self, name, source)

    def begin_group(self) -> GroupWriter:
        """Start a group of new sequences committed together: ``add`` each, then ``commit``
        (one fsync of their rows, one LMDB transaction; each sequence whole or absent). See
        :mod:`sprint_map.storage.group_writer`."""
        return GroupWriter(self)

    def sequence_digest(self, seq_id: int, txn: lmdb.Transaction) -> bytes | None:
        """The content digest committed with sequence ``seq_id`` (None: written before digests
        were recorded). O(log n_sequences)."""
        if not self.env.has_db("digests"):
            return None
        raw = txn.get(u32(seq_id), db=self.env.db("digests"))
        return None if raw is None else bytes(raw)

    def put_lookups(self, txn: lmdb.Transaction, record: SequenceRecord) -> None:
        """Write the name and vertex-range index entries of ``record`` (derived from it)."""
        txn.put(record.name.encode(), u32(record.seq_id), db=self.env.db("seq_names"))
        txn.put(u64(record.last_vertex), u32(record.seq_id), db=self.env.db("vrange"))

    def after_commit(self, first: int, frames: int) -> None:
        """Vertices ``first .. first+frames-1`` were just committed: the index catches up from
        the shards (page cache) and says when its files are due (the flat file on a geometric
        schedule, a full tail block of the segmented index); they are persisted then."""
        if self.index.after_commit(first + frames, self.shards, first):
            if self._grouped:
                self._persist_due = True
            else:
                self.flush()
        if not self._grouped:
            self._learn_if_due()

    def _learn_if_due(self) -> None:
        """Retrain the projection after ``learn_every`` new edges (past a commit point: a
        failure is a warning, the map keeps the projection it had)."""
        try:
            if learning.due(self):
                report = learning.learn(self)
                self.index.events.append(f"learned from {report.pairs} merged pairs: "
                                         f"{'adopted' if report.adopted else 'not adopted'}")
        except (OSError, ValueError, np.linalg.LinAlgError) as exc:
            self.warnings.append(f"the descriptor projection was not retrained ({exc})")

    def learn(self) -> LearnReport:
        """Learn the projection from the merged edges (``index --learn``); see
        :func:`sprint_map.storage.learning.learn`. StorageIOError if a file cannot be written."""
        try:
            return learning.learn(self)
        except OSError as exc:
            raise StorageIOError(f"cannot write the index in {self.data_path / INDEX_DIR}: "
                                 f"{exc.strerror or exc}") from exc

    def unlearn(self) -> bool:
        """Drop the learned projection (``index --no-learn``); False if there was none."""
        try:
            return learning.unlearn(self)
        except OSError as exc:
            raise StorageIOError(f"cannot write the index in {self.data_path / INDEX_DIR}: "
                                 f"{exc.strerror or exc}") from exc

    @contextlib.contextmanager
    def group_commit(self) -> Iterator[None]:
        """Commit several sequences one after the other as a group: each is still its own
        atomic, durable commit (rows fsynced once, then its LMDB transaction; what localised
        drives need, each seen by the next), but the index is persisted once, at the end of
        the group, if one of them made it due. Nests. (Sequences that need not see each other
        share one transaction instead: :meth:`begin_group`.)

        Notes
        -----
        A kill inside the group loses no committed sequence: the index is a cache that catches
        up from the shards on the next load.
        """
        self.require_writer()
        self._grouped += 1
        try:
            yield
        finally:
            self._grouped -= 1
            if not self._grouped and self._persist_due:
                self._persist_due = False
                try:
                    self.flush()
                except StorageIOError as exc:  # the sequences are committed: a warning
                    self.warnings.append(f"the index cache was not saved ({exc})")
            if not self._grouped:
                self._learn_if_due()



def _undo_create(created: list[Path]) -> None:
    """Remove what a failed :meth:`MapStore.create` made, newest first, and nothing else: the
    directories it created (with the files LMDB put in them) and the lock file. Best effort:
    an error here must not mask the one that failed the creation."""
    for path in reversed(created):
        with contextlib.suppress(OSError):
            if path.is_dir() and not path.is_symlink():
                for entry in path.iterdir():  # LMDB's data.mdb/lock.mdb; our dirs are flat
                    if entry.is_file() or entry.is_symlink():
                        entry.unlink()
                path.rmdir()
            else:
                path.unlink()


def decode_config(data: Any) -> StoreConfig:
    """The storage fields of the map's stored config record (decoded JSON), or
    MapCorruptError if it is not a valid config (:func:`decode_stored_config`; the facade
    checks the other fields the same way, ``sprint_map.map``). O(fields)."""
    return decode_stored_config(StoreConfig.from_record, data)


def is_map(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` looks like a map directory (cheap, no open)."""
    root = Path(path)
    try:
        return (current_data(root) / LMDB_DIR / "data.mdb").is_file()
    except SprintMapError:
        return False


__all__ = [
    "MapStore",
    "SprintMapError",
    "is_map",
    "validate_descriptors",
]
