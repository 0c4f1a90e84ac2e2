"""The retrieval index of a map: exact flat while small, segmented and approximate when large.

Which index a map uses follows ``StoreConfig.index_type``:

* ``"flat"``: :class:`~sprint_map.storage.index.flat.FlatIndex`, exact, one file
  ``flat.<upto>.faiss`` rewritten geometrically (every map created before the approximate
  indexes);
* ``"ivf-pq"`` / ``"ivf-sq8"``: :class:`~sprint_map.storage.index.segmented.SegmentedIndex`,
  trained as soon as the map holds ``MIN_TRAIN`` vertices (flat until then);
* ``"auto"`` (the default): flat until ``vertices * dim`` reaches ``index_auto_vertices``
  128-dimensional vertices' worth, then ``ivf-pq``, trained by the writer when the map
  crosses that size.

Both implement :class:`~sprint_map.storage.index.base.RetrievalIndex`; the store holds
one of them, the *active* index, and switching kind (``index --train``, a map growing past
the threshold) is replacing it. Both are caches of the shards (LMDB is the truth): files ahead
of the map or torn are dropped by the writer's open, the in-memory index is caught up from the
shards when loaded. A writer switching kind publishes the new index first and only then
removes the old kind's files, so readers keep searching the old index until the new one is
complete; a publication of a later kind in :data:`KINDS` supersedes the files of an earlier one.

A map may search a projection learned from its merged edges
(:mod:`~sprint_map.storage.index.projection`). Its index then lives in its own directory
``index/pGGGGGG/`` (the projection's file beside the index's), and ``index/learned.json``, the
pointer, names it: publishing the pointer is the commit point of learning or dropping one
(:meth:`IndexStore.install`). Without a pointer (every map made before learning) the index
files are in ``index/`` itself, as they always were.
"""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import replace
from pathlib import Path
from typing import Any

from sprint_map.storage.index.base import RetrievalIndex
from sprint_map.storage.index.flat import FlatIndex, file_bytes, file_problem, index_files
from sprint_map.storage.index.model import MIN_TRAIN, publish_bytes
from sprint_map.storage.index.projection import (
    LEARNED,
    PROJECTION_FILE,
    Learned,
    Projection,
    checksum_bytes,
    read_learned,
)
from sprint_map.storage.index.segmented import SegmentedIndex
from sprint_map.storage.shards import ShardSet
from sprint_map.storage.store_config import StoreConfig
from sprint_map.testing.crash import crash_point
from sprint_map.util import atomic
from sprint_map.util.arrays import Descriptors, SearchResult

__all__ = ["KINDS", "IndexStore", "approximate_kind", "file_bytes", "file_problem",
           "index_files", "projection_dirs"]

PROJECTION_DIR_RE = re.compile(r"^p(\d{6})$")


def projection_dirs(directory: Path) -> list[Path]:
    """The projection directories ``pGGGGGG`` in ``directory`` (``index/``). O(entries)."""
    if not directory.is_dir():
        return []
    return sorted(e for e in directory.iterdir() if PROJECTION_DIR_RE.match(e.name))

#: Every kind of index, in ascending precedence: a publication of a later kind supersedes
#: the files of the earlier ones (they are leftovers of a kill before their removal).
KINDS: tuple[type[RetrievalIndex], ...] = (FlatIndex, SegmentedIndex)


def approximate_kind(config: StoreConfig, committed: int) -> str | None:
    """The approximate index kind a map of ``committed`` vertices should use, or None (flat)."""
    if committed < MIN_TRAIN or config.index_type == "flat":
        return None
    if config.index_type == "auto":
        big = committed * config.dim >= config.index_auto_vertices * 128
        return "ivf-pq" if big else None
    return config.index_type


class IndexStore:
    """The map's index: one active :class:`RetrievalIndex`, its kind chosen on load.

    The active index is loaded, or an unloaded :class:`FlatIndex` (nothing loaded yet).

    Parameters
    ----------
    directory : Path
        The ``index/`` directory.
    dim : int
        Descriptor dimension.
    writable : bool
        Whether this process may write files (only the writer persists, trains or deletes).
    config : StoreConfig, optional
        The map's config (default: a flat index of ``dim``).
    """

    def __init__(self, directory: Path, dim: int, *, writable: bool,
                 config: StoreConfig | None = None) -> None:
        self.directory = directory
        self.dim = dim
        self.writable = writable
        self.config = config if config is not None else StoreConfig(dim=dim, index_type="flat")
        self.events: list[str] = []  # what loading had to do (for check/info reports)
        #: The projection pointer the active index follows, and its projection once read.
        self.learned = Learned()
        self.projection: Projection | None = None
        self._pinned = False  # install() builds under a pointer not yet published
        self.active: RetrievalIndex = self._make(FlatIndex)
        #: Seconds spent training (and encoding the map with) new models in this process.
        self.train_s = 0.0
        self._shards: ShardSet | None = None
        self._committed = 0
        #: Leave the growth retraining to :meth:`retrain_beside` (a service: the commit path
        #: holds every session while it runs) instead of doing it in :meth:`after_commit`.
        self.defer_retrain = False

    def _make(self, kind: type[RetrievalIndex]) -> RetrievalIndex:
        """A new, unloaded index of ``kind`` in the directory of the followed projection
        (``index/`` without one). O(1): nothing is read."""
        learned = self.learned
        if not learned.generation:
            return kind(self.directory, self.config, writable=self.writable, events=self.events)
        return kind(self.directory / learned.directory_name,
                    replace(self.config, dim=learned.dim_out), writable=self.writable,
                    events=self.events, projection=self.projection)

    # --- the learned projection --------------------------------------------------------------
    def _sync(self, matrix: bool = False) -> None:
        """Follow the published pointer while nothing is loaded (a loaded index keeps the
        projection it was loaded with); with ``matrix`` also read and verify the projection.
        A garbled pointer or projection is a cache event: the plain descriptor is searched.
        One small file read (plus O(projection bytes) with ``matrix``)."""
        if self.active.loaded or self._pinned:
            return
        try:
            learned = read_learned(self.directory)
        except (ValueError, OSError) as exc:
            self.events.append(f"projection pointer unusable ({exc}); plain descriptor used")
            learned = Learned()
        if learned.generation != self.learned.generation:
            self.projection = None
        self.learned = learned
        if matrix or self.projection is None:
            self.active = self._make(FlatIndex)
        if matrix and learned.generation and self.projection is None:
            try:
                self.projection = learned.read_projection(self.directory)
            except (ValueError, OSError) as exc:
                self.events.append(f"projection unusable ({exc}); plain descriptor used")
                self.learned = Learned(attempted_at_edges=learned.attempted_at_edges)
            self.active = self._make(FlatIndex)

    def learned_state(self) -> Learned:
        """The published pointer (what ``info`` reports; ``Learned()`` if none or garbled).
        One small file read."""
        self._sync()
        return self.learned

    def install(self, learned: Learned, projection: Projection | None, committed: int,
                shards: ShardSet) -> None:
        """Make ``projection`` (None: the plain descriptor) the map's, with ``learned``'s
        record, and the index built under it; the writer only.

        A new projection gets a new directory ``index/pGGGGGG/``: its file, then its whole
        index are published there (``learn.projection_written``, ``learn.index_built``) while
        readers keep the old index; then the pointer (``learn.published``, the commit point);
        then the old projection's directory (or the plain index's files) is deleted. A kill
        leaves the old projection with its index or the new one with its index; the next
        writer's open deletes what the pointer does not name.

        Notes
        -----
        O(projection bytes) plus a rebuild of the index (O(committed * dim) and training).
        """
        assert self.writable
        self._sync()
        old, old_projection = self.learned, self.projection
        self.reset()
        if projection is not None:
            numbers = [int(d.name[1:]) for d in projection_dirs(self.directory)]
            generation = 1 + max(numbers + [old.generation])
            learned = replace(learned, generation=generation)
            target = self.directory / learned.directory_name
            target.mkdir()
            atomic.fsync_dir(self.directory)
            data = projection.to_bytes()
            publish_bytes(target / PROJECTION_FILE, data)
            learned = replace(learned, file_bytes=len(data), checksum=checksum_bytes(data),
                              dim_in=projection.dim_in, dim_out=projection.dim_out)
            crash_point("learn.projection_written")
        else:
            learned = Learned(attempted_at_edges=learned.attempted_at_edges)
        if learned.generation != old.generation:
            self.learned, self.projection = learned, projection
            self._pinned = True
            try:
                self.active = self._make(FlatIndex)
                self.rebuild(committed, shards)
            except BaseException:
                self.reset()
                self.learned, self.projection = old, old_projection
                self.active = self._make(FlatIndex)
                raise
            finally:
                self._pinned = False
            crash_point("learn.index_built")
        publish_bytes(self.directory / LEARNED, learned.encode())
        crash_point("learn.published")
        self.learned, self.projection = learned, projection
        if old.generation != learned.generation:
            self._remove_followed(old)

    def record_attempt(self, edges: int) -> None:
        """Record a learning attempt at ``edges`` that changed nothing (the pointer is
        republished with it; the projection in use stays). One small file published."""
        assert self.writable
        self._sync()
        publish_bytes(self.directory / LEARNED,
                      replace(self.learned, attempted_at_edges=edges).encode())
        self.learned = replace(self.learned, attempted_at_edges=edges)

    def _remove_followed(self, learned: Learned) -> list[str]:
        """Delete the index files of ``learned`` (its directory; without a projection the
        plain index's files in ``index/``). Returns what was removed."""
        if learned.generation:
            target = self.directory / learned.directory_name
            if not target.exists():
                return []
            atomic.remove_tree(target)
            atomic.fsync_dir(self.directory)
            return [target.name]
        removed = []
        for kind in KINDS:
            removed.extend(kind(self.directory, self.config, writable=True).remove_files())
        return removed

    def adopt(self, other: IndexStore) -> None:
        """Publish ``other``'s projection and pointer here (``compact``'s new generation,
        before its index is built). O(projection bytes)."""
        assert self.writable
        other._sync(matrix=True)
        learned, projection = other.learned, other.projection
        if not learned.generation and not learned.attempted_at_edges:
            return
        if projection is not None:
            target = self.directory / learned.directory_name
            target.mkdir(parents=True, exist_ok=True)
            publish_bytes(target / PROJECTION_FILE, projection.to_bytes())
        publish_bytes(self.directory / LEARNED, learned.encode())
        self.learned, self.projection = learned, projection
        self.active = self._make(FlatIndex)

    def _replace(self, index: RetrievalIndex) -> None:
        """Make ``index`` the active one; the old one is closed (its memory released)."""
        old, self.active = self.active, index
        if old is not index:
            old.close()

    def _on_disk(self) -> RetrievalIndex:
        """An unloaded index of the kind whose files are published (flat if none)."""
        self._sync()
        for kind in reversed(KINDS[1:]):
            index = self._make(kind)
            if index.published():
                return index
        return self._make(KINDS[0])

    # --- state ------------------------------------------------------------------------------
    @property
    def index(self) -> RetrievalIndex | None:
        """The loaded index (None until the first search)."""
        return self.active if self.active.loaded else None

    @property
    def covered(self) -> int:
        """Vertices covered by the in-memory index (0 if not loaded)."""
        return self.active.covered

    @property
    def persisted(self) -> int:
        """Vertices the trusted files on disk cover (sealed segments, or the flat file)."""
        return self.active.persisted

    def persisted_on_disk(self) -> int:
        """Vertices covered by the index files on disk (without loading them)."""
        return self._on_disk().persisted_on_disk()

    def has_files(self) -> bool:
        """Whether an index is persisted at all (a flat file, or a segment manifest)."""
        self._sync()
        return any(self._make(kind).has_files() for kind in KINDS)

    def describe(self) -> dict[str, Any]:
        """What ``info`` reports about the index (loaded or not)."""
        return (self.active if self.active.loaded else self._on_disk()).describe()

    # --- opening ------------------------------------------------------------------------------
    def discard_untrusted(self, committed: int) -> list[str]:
        """Drop index files ahead of ``committed`` vertices, torn, not named, or superseded by
        a later kind's publication (writer, open).

        Notes
        -----
        One ``stat`` per index file: O(segments), O(log map size) with tiered merging.
        """
        actions = self._discard_projections()
        for kind in KINDS:
            actions.extend(self._make(kind).discard_untrusted(committed))
        winner = self._on_disk()
        for kind in KINDS[: KINDS.index(type(winner))]:
            actions.extend(f"removed index {name}: superseded by {winner.files}"
                           for name in self._make(kind).remove_files())
        return actions

    def _discard_projections(self) -> list[str]:
        """Drop a garbled pointer or a projection failing its checks (the plain descriptor
        again), projection directories the pointer does not name (a kill before or after its
        publication) and, when it names one, the plain index's files. O(projection bytes)."""
        actions = []
        self.reset()
        try:
            learned = read_learned(self.directory)
        except ValueError as exc:
            learned = Learned()
            atomic.unlink(self.directory / LEARNED)
            actions.append(f"removed the projection pointer {LEARNED}: {exc}")
        if learned.generation:
            try:
                learned.read_projection(self.directory)
            except (ValueError, OSError) as exc:
                actions.append(f"dropped the learned projection: {exc}")
                learned = Learned(attempted_at_edges=learned.attempted_at_edges)
                publish_bytes(self.directory / LEARNED, learned.encode())
        for entry in projection_dirs(self.directory):
            if entry.name != (learned.directory_name if learned.generation else None):
                atomic.remove_tree(entry)
                actions.append(f"removed index {entry.name}/: not the learned projection")
        if learned.generation:
            actions.extend(f"removed index {name}: superseded by the learned projection"
                           for name in self._remove_followed(Learned()))
            actions.extend(f"removed leftover temp file {learned.directory_name}/{p.name}"
                           for p in atomic.remove_partials(self.directory
                                                           / learned.directory_name))
        if actions:
            atomic.fsync_dir(self.directory)
        self.learned, self.projection = Learned(), None
        self._sync()
        return actions

    def load(self, committed: int, shards: ShardSet) -> None:
        """Load the trusted index and bring it up to ``committed`` vertices.

        A loaded index is only caught up, unless it is exact and the map (a writer's) should
        use the approximate index now: the published segments are opened, or trained here.
        Nothing loaded: the segments if the config allows them and they are published, else
        the flat index.
        """
        self._shards, self._committed = shards, committed
        self._sync(matrix=True)
        train = self.writable and approximate_kind(self.config, committed) is not None
        active = self.active
        if active.loaded and not (train and active.exact):
            self.catch_up(committed, shards)
            return
        if self.config.index_type != "flat":
            segmented = self._make(SegmentedIndex)
            if segmented.load(committed, shards):
                self._replace(segmented)
                return
            if train:
                self.train(committed, shards)
                return
        flat = active if active.exact else self._make(FlatIndex)
        self._replace(flat)
        flat.load(committed, shards)

    def catch_up(self, committed: int, shards: ShardSet) -> None:
        """Add shard rows ``covered..committed-1`` to the in-memory index."""
        self._shards, self._committed = shards, committed
        if self.active.outdated():  # a reader far behind the writer's segments: reopen them
            self.reset()
            self.load(committed, shards)
            return
        self.active.catch_up(committed, shards)

    def search(self, queries: Descriptors, k: int) -> SearchResult:
        """k nearest vertices of each query row: ``(squared L2 distances, vertex_ids)``.

        Distances are exact for both kinds (the segmented index re-ranks from the shards);
        rows are -1 padded. Asking for a larger ``k`` (e.g. to filter removed vertices) costs
        ``max(k, index_rerank)`` candidates, not another search.
        """
        return self.active.search(queries, k)

    def search_within(self, queries: Descriptors, k: int, start: int, stop: int
                      ) -> SearchResult:
        """:meth:`search` among vertex ids ``[start, stop)`` only, on the approximate index
        (a retrieval shard's range); ValueError while the index is the exact flat one.
        Cost: the segments holding ids of the range, not the others."""
        active = self.active
        if not isinstance(active, SegmentedIndex):
            raise ValueError("a search within a vertex range needs the approximate index; "
                             "this map's index is exact")
        return active.search(queries, k, (start, stop))

    def segment_bounds(self) -> list[tuple[int, int]]:
        """The ``(start, stop)`` vertex ids of each sealed segment, in order (none for the
        exact index). O(segments)."""
        active = self.active
        if not isinstance(active, SegmentedIndex) or not active.loaded:
            return []
        return [(s.start, s.stop) for s in active.manifest.segments]

    # --- writing ------------------------------------------------------------------------------
    def after_commit(self, committed: int, shards: ShardSet, first: int) -> bool:
        """Update the index after a commit of vertices ``first..committed-1``; True if the
        caller should persist (flat: on the geometric schedule; segmented: never, a full
        tail block is sealed in the background)."""
        if self.active.loaded:
            if self.covered == first:
                # The rows are in the page cache: read them back from the shards' memory map.
                self.catch_up(committed, shards)
            else:  # cannot happen with one writer; reload rather than guess
                self.reset()
        self._shards, self._committed = shards, committed
        if approximate_kind(self.config, committed) is not None and self.active.exact:
            self.load(committed, shards)  # the published segments, or train them now
        if not self.defer_retrain and self.retrain_due(committed):
            self.train(committed, shards)
        return self.active.after_commit(committed, shards)

    def retrain_beside(self, committed: int, shards: ShardSet,
                       exclusive: Callable[[], AbstractContextManager[object]]) -> bool:
        """The growth retraining (:meth:`retrain_due`) with searches going on: the new
        generation is trained and encoded while this index keeps answering from the old one,
        and only the switch runs under ``exclusive()`` (the caller's lock against searches
        and commits of this process). The writer's thread, between commits: nothing may
        commit or seal meanwhile. True if the index was retrained.

        Crash safe like :meth:`train`: the new files are named by the manifest published at
        the switch; a kill before it leaves unnamed files, removed by the next writer's open.

        Notes
        -----
        What :meth:`train` costs, outside the lock; under it, a seal in flight finishing,
        then O(segments) to open the new ones and the tail's catch-up.
        """
        assert self.writable
        active = self.active
        if not self.retrain_due(committed) or not isinstance(active, SegmentedIndex):
            return False
        with exclusive():
            active.wait()  # the old generation publishes nothing more until the switch
            fresh = self._make(SegmentedIndex)
        assert isinstance(fresh, SegmentedIndex)
        started = time.perf_counter()
        try:
            fresh.rebuild(committed, shards, publish=False)
        except OSError as exc:  # the old index goes on; the unnamed files go at the next open
            fresh.close()
            self.events.append(f"index retraining failed ({exc.strerror or exc}); the "
                               "previous generation is kept")
            return False
        with exclusive():
            try:
                fresh.finish(committed, shards)
            except OSError as exc:  # the old index (files and all) still answers here
                fresh.close()
                self.events.append(f"index retraining not installed ({exc.strerror or exc})")
                return False
            old, self.active = self.active, fresh
            old.close()
        self._shards, self._committed = shards, committed
        self.train_s += time.perf_counter() - started
        desc = fresh.describe()
        self.events.append(f"index trained again beside searches: {desc['type']}, "
                           f"{desc['segments']} segments")
        return True

    def retrain_due(self, committed: int) -> bool:
        """Whether the loaded approximate index's model was trained on a map
        ``index_retrain_growth`` times smaller than ``committed`` (never with growth 0).

        Notes
        -----
        O(1). A retraining costs what :meth:`train` costs; at growth ``g`` every vertex is
        encoded ``g / (g - 1)`` times over the map's life (4/3 at the default 4).
        """
        growth = self.config.index_retrain_growth
        active = self.active
        if not growth or not isinstance(active, SegmentedIndex) or not active.loaded:
            return False
        return committed >= growth * max(active.manifest.trained_on, 1)

    def persist(self) -> bool:
        """Make the files cover what they should: seal full tail blocks (segmented), train
        (a map that crossed the approximate threshold) or publish the flat index."""
        if not self.writable:
            return False
        shards, committed = self._shards, self._committed
        if shards is None:
            return False  # nothing added or searched since the open: nothing to persist
        if approximate_kind(self.config, committed) is not None and self.active.exact:
            self.load(committed, shards)  # opens the published segments, or trains
        return self.active.persist()

    def train(self, committed: int, shards: ShardSet) -> list[str]:
        """Train a new model on a fresh sample and re-encode every vertex (``index --train``).

        The new generation's files are published under new names and the manifest replaced
        last: readers keep the old index until then; a kill leaves the old one (its files
        named by the old manifest) or the new one. Falls back to a flat rebuild when the map
        is too small for the approximate index its config asks for.

        Notes
        -----
        Training plus O(committed * dim) to re-encode.
        """
        assert self.writable
        self._sync(matrix=True)
        if approximate_kind(self.config, committed) is None:
            self.rebuild(committed, shards)
            return [f"rebuilt the flat index ({committed} vertices)"]
        self.train_s += self._rebuild_as(SegmentedIndex, committed, shards)
        desc = self.active.describe()
        self.events.append(f"index trained: {desc['type']}, {desc['segments']} segments")
        return [f"trained {desc['type']} on {committed} vertices: {desc['segments']} "
                f"segments, {desc['tail']} tail vertices searched exactly"]

    def rebuild(self, committed: int, shards: ShardSet) -> None:
        """Rebuild the index from the shards and publish it in place of every index file.

        The segmented index is retrained (a new generation); the flat one rewritten.
        """
        assert self.writable
        self._sync(matrix=True)
        if approximate_kind(self.config, committed) is not None:
            self.train(committed, shards)
            return
        self._rebuild_as(FlatIndex, committed, shards)

    def _rebuild_as(self, kind: type[RetrievalIndex], committed: int, shards: ShardSet
                    ) -> float:
        """Make a rebuilt index of ``kind`` the active one, then delete every other kind's
        files; returns the seconds the rebuild took. A failure leaves nothing loaded."""
        self._shards, self._committed = shards, committed
        self.reset()  # a sealing in flight finishes first
        fresh = self._make(kind)
        started = time.perf_counter()
        fresh.rebuild(committed, shards)
        elapsed = time.perf_counter() - started
        self.active = fresh
        for other in KINDS:
            if other is not kind:
                self._make(other).remove_files()
        return elapsed

    def merge_segments(self) -> bool:
        """Merge the sealed segments into as few as ``index_segment_max_rows`` allows
        (``compact``); False if nothing to merge.

        Published like a seal (segment file, then manifest): a kill leaves the old segments
        or the merged one. O(sealed codes) read and written.
        """
        assert self.writable
        return self.active.merge()

    def close(self) -> None:
        """Finish a sealing in flight before this index is dropped (e.g. its generation's
        directory removed by ``compact``); its error, if any, only loses that seal."""
        try:
            self.reset()
        except OSError as exc:
            self.events.append(f"segment sealing in flight failed ({exc}); sealed later")

    def reset(self) -> None:
        """Forget the in-memory index (it is reloaded on the next search)."""
        old, self.active = self.active, self._make(FlatIndex)
        old.close()
