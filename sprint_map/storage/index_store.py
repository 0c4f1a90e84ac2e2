"""The retrieval index of a map: exact flat while small, segmented and approximate when large.

Which index a map uses follows ``MapConfig.index_type``:

* ``"flat"``: :class:`~sprint_map.storage.flat_index.FlatIndex`, exact, one file
  ``flat.<upto>.faiss`` rewritten geometrically (every map created before the approximate
  indexes);
* ``"ivf-pq"`` / ``"ivf-sq8"``: :class:`~sprint_map.storage.segment_index.SegmentedIndex`,
  trained as soon as the map holds ``MIN_TRAIN`` vertices (flat until then);
* ``"auto"`` (the default): flat until ``vertices * dim`` reaches ``index_auto_vertices``
  128-dimensional vertices' worth, then ``ivf-pq``, trained by the writer when the map
  crosses that size.

Both are caches of the shards (LMDB is the truth): files ahead of the map or torn are dropped
by the writer's open, the in-memory index is caught up from the shards when loaded. A writer
switching to the segmented index publishes its manifest first and only then removes the flat
files, so readers keep searching the old index until the new one is complete.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map.config import MapConfig
from sprint_map.errors import StorageIOError
from sprint_map.storage import atomic
from sprint_map.storage.flat_index import FlatIndex, file_bytes, file_problem, index_files
from sprint_map.storage.segment_index import (
    SegmentedIndex,
    manifest_problems,
    publish_manifest,
    read_manifest,
    remove_unlisted,
)
from sprint_map.storage.segment_model import MIN_TRAIN
from sprint_map.storage.shards import ShardSet

__all__ = ["IndexStore", "file_bytes", "file_problem", "index_files"]


def approximate_kind(config: MapConfig, committed: int) -> str | None:
    """The approximate index kind a map of ``committed`` vertices should use, or None (flat)."""
    if committed < MIN_TRAIN or config.index_type == "flat":
        return None
    if config.index_type == "auto":
        big = committed * config.dim >= config.index_auto_vertices * 128
        return "ivf-pq" if big else None
    return config.index_type


class IndexStore:
    """The map's index: a :class:`FlatIndex` or a :class:`SegmentedIndex`, chosen on load.

    Parameters
    ----------
    directory : Path
        The ``index/`` directory.
    dim : int
        Descriptor dimension.
    writable : bool
        Whether this process may write files (only the writer persists, trains or deletes).
    config : MapConfig, optional
        The map's config (default: a flat index of ``dim``).
    """

    def __init__(self, directory: Path, dim: int, *, writable: bool,
                 config: MapConfig | None = None) -> None:
        self.directory = directory
        self.dim = dim
        self.writable = writable
        self.config = config if config is not None else MapConfig(dim=dim, index_type="flat")
        self.flat = FlatIndex(directory, dim, writable=writable)
        self.segmented: SegmentedIndex | None = None
        self.events = self.flat.events  # what loading had to do (for check/info reports)
        #: Seconds spent training (and encoding the map with) new models in this process.
        self.train_s = 0.0
        self._shards: ShardSet | None = None
        self._committed = 0

    # --- state ------------------------------------------------------------------------------
    @property
    def index(self) -> Any:
        """The loaded index (None until the first search)."""
        return self.segmented if self.segmented is not None else self.flat.index

    @property
    def covered(self) -> int:
        """Vertices covered by the in-memory index (0 if not loaded)."""
        return self.segmented.covered if self.segmented is not None else self.flat.covered

    @property
    def persisted(self) -> int:
        """Vertices the trusted files on disk cover (sealed segments, or the flat file)."""
        if self.segmented is not None:
            return self.segmented.manifest.sealed
        return self.flat.persisted

    @persisted.setter
    def persisted(self, value: int) -> None:
        self.flat.persisted = value

    def persisted_on_disk(self) -> int:
        """Vertices covered by the index files on disk (without loading them)."""
        try:
            manifest = read_manifest(self.directory)
        except ValueError:
            manifest = None
        if manifest is not None:
            return manifest.sealed
        return self.flat.persisted_on_disk()

    def has_files(self) -> bool:
        """Whether an index is persisted at all (a flat file, or a segment manifest)."""
        return (self.directory / "segments.json").exists() or bool(index_files(self.directory))

    def describe(self) -> dict[str, Any]:
        """What ``info`` reports about the index (loaded or not)."""
        if self.segmented is not None:
            return self.segmented.describe()
        try:
            manifest = read_manifest(self.directory)
        except ValueError:
            manifest = None
        if manifest is not None:
            return {"type": f"segmented {manifest.kind} (IVF{manifest.nlist})",
                    "generation": manifest.generation, "segments": len(manifest.segments),
                    "sealed": manifest.sealed}
        return {"type": "IndexIDMap2(IndexFlatL2)"}

    # --- opening ------------------------------------------------------------------------------
    def discard_untrusted(self, committed: int) -> list[str]:
        """Drop index files ahead of ``committed`` vertices, torn, or not named (writer, open).

        Notes
        -----
        One ``stat`` per index file: O(segments), O(log map size) with tiered merging.
        """
        actions = self.flat.discard_untrusted(committed)
        try:
            manifest = read_manifest(self.directory)
        except ValueError as exc:
            actions.append(f"removed the index manifest: {exc}")
            manifest = None
        if manifest is not None:
            model_problem, good, problems = manifest_problems(self.directory, manifest,
                                                              committed)
            actions.extend(f"index {problem}: dropped" for problem in problems)
            if model_problem:
                manifest = None
            elif good < len(manifest.segments):
                manifest = replace(manifest, segments=manifest.segments[:good])
                publish_manifest(self.directory, manifest)
        actions.extend(f"removed index {name}: not in the manifest"
                       for name in remove_unlisted(self.directory, manifest))
        if manifest is not None and index_files(self.directory):
            for _, path in index_files(self.directory):  # superseded by the segments
                atomic.unlink(path)
                actions.append(f"removed index {path.name}: superseded by the segments")
            atomic.fsync_dir(self.directory)
        return actions

    def load(self, committed: int, shards: ShardSet) -> Any:
        """Load the trusted index and bring it up to ``committed`` vertices.

        A writer whose map should use the approximate index but has none trains it here.
        """
        self._shards, self._committed = shards, committed
        if self.segmented is not None:
            self.catch_up(committed, shards)
            return self.segmented
        wants = approximate_kind(self.config, committed)
        if self.config.index_type != "flat" and (
                self.flat.index is None or (self.writable and wants is not None)):
            opened = None
            for attempt in range(3):  # a reader may race the writer replacing merged segments
                opened = SegmentedIndex.open(self.directory, self.config, committed, self.events,
                                             strict=not self.writable and attempt < 2)
                if opened is not None or not (self.directory / "segments.json").exists():
                    break
            if opened is not None:
                self.segmented = opened
                self.flat.reset()
                opened.catch_up(committed, shards)
                return opened
            if wants is not None and self.writable:
                self.train(committed, shards)
                return self.segmented
        return self.flat.load(committed, shards)

    def catch_up(self, committed: int, shards: ShardSet) -> None:
        """Add shard rows ``covered..committed-1`` to the in-memory index."""
        self._shards, self._committed = shards, committed
        if self.segmented is not None:
            if not self.writable and self.segmented.tail_len > 2 * self.config.index_segment_rows:
                self.reset()  # a reader far behind the writer's segments: reopen them
                self.load(committed, shards)
                return
            self.segmented.catch_up(committed, shards)
        else:
            self.flat.catch_up(committed, shards)

    def search(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """k nearest vertices of each query row: ``(squared L2 distances, vertex_ids)``.

        Distances are exact for both kinds (the segmented index re-ranks from the shards);
        rows are -1 padded. Asking for a larger ``k`` (e.g. to filter removed vertices) costs
        ``max(k, index_rerank)`` candidates, not another search.
        """
        if self.segmented is not None:
            assert self._shards is not None
            # Every covered row was committed, even when the last load() was an older
            # snapshot's (storage/snapshot.py): its re-ranking may read them all.
            committed = max(self._committed, self.covered)
            return self.segmented.search(queries, k, self._shards, committed)
        return self.flat.search(queries, k)

    # --- writing ------------------------------------------------------------------------------
    def after_commit(self, committed: int, shards: ShardSet, first: int) -> bool:
        """Update the index after a commit of vertices ``first..committed-1``; True if the
        caller should persist (flat: on the geometric schedule; segmented: a tail to seal)."""
        if self.index is not None:
            if self.covered == first:
                # The rows are in the page cache: read them back from the shards' memory map.
                self.catch_up(committed, shards)
            else:  # cannot happen with one writer; reload rather than guess
                self.reset()
        self._shards, self._committed = shards, committed
        kind = approximate_kind(self.config, committed)
        if kind is not None and self.segmented is None:
            self.load(committed, shards)  # the published segments, or train them now
        if self.segmented is not None:
            try:  # sealing runs in a worker thread: the commit path does not wait for it
                self.segmented.seal_ready(shards, committed, background=True)
            except OSError as exc:
                raise StorageIOError(f"cannot seal an index segment in {self.directory}: "
                                     f"{exc.strerror or exc}") from exc
            return False
        on_disk = self.flat.persisted if self.flat.index is not None else (
            self.flat.persisted_on_disk())
        # A flat index file is rewritten whole on every persist, so the interval grows with the
        # file (geometric): total bytes written stay O(final size), not O(size^2 / interval).
        cfg = self.config
        due = committed - on_disk >= max(cfg.index_persist_every,
                                         cfg.index_persist_growth * on_disk)
        if due and self.flat.index is None:
            self.flat.load(committed, shards)
        return due

    def persist(self) -> bool:
        """Make the files cover what they should: seal full tail blocks (segmented), train
        (a map that crossed the approximate threshold) or publish the flat index."""
        if not self.writable:
            return False
        shards, committed = self._shards, self._committed
        if shards is None:
            return False  # nothing added or searched since the open: nothing to persist
        if approximate_kind(self.config, committed) is not None:
            if self.segmented is None:
                self.load(committed, shards)  # opens the published segments, or trains
            if self.segmented is not None:
                self.segmented.wait()  # the worker's block first, then every full one
                return self.segmented.seal_ready(shards, committed)
        return self.flat.persist()

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
        if self.segmented is not None:
            self.segmented.wait()
        kind = approximate_kind(self.config, committed)
        if kind is None:
            self.rebuild(committed, shards)
            return [f"rebuilt the flat index ({committed} vertices)"]
        self._shards, self._committed = shards, committed
        generation = 1 + max([int(p.name.split(".")[1]) for p in
                              self.directory.glob("model.*.faiss")] + [0])
        started = time.perf_counter()
        self.segmented = SegmentedIndex.train(self.directory, self.config, kind, committed,
                                              shards, generation)
        self.train_s += time.perf_counter() - started
        self.flat.index = None
        self.flat.persisted = 0
        remove_unlisted(self.directory, self.segmented.manifest)
        for _, path in index_files(self.directory):
            atomic.unlink(path)
        atomic.fsync_dir(self.directory)
        desc = self.segmented.describe()
        self.events.append(f"index trained: {desc['type']}, {desc['segments']} segments")
        return [f"trained {desc['type']} on {committed} vertices: {desc['segments']} "
                f"segments, {desc['tail']} tail vertices searched exactly"]

    def rebuild(self, committed: int, shards: ShardSet) -> None:
        """Rebuild the index from the shards and publish it in place of every index file.

        The segmented index is retrained (a new generation); the flat one rewritten.
        """
        assert self.writable
        if approximate_kind(self.config, committed) is not None:
            self.train(committed, shards)
            return
        if self.segmented is not None:
            self.segmented.wait()
        self.segmented = None
        self.flat.rebuild(committed, shards)
        remove_unlisted(self.directory, None)

    def merge_segments(self) -> bool:
        """Merge every sealed segment into one (``compact``); False if nothing to merge.

        Published like a seal (segment file, then manifest): a kill leaves the old segments
        or the merged one. O(sealed codes) read and written.
        """
        assert self.writable
        if self.segmented is None:
            return False
        return self.segmented.merge_all()

    def close(self) -> None:
        """Finish a sealing in flight before this index is dropped (e.g. its generation's
        directory removed by ``compact``); its error, if any, only loses that seal."""
        if self.segmented is not None:
            try:
                self.segmented.wait()
            except OSError as exc:
                self.events.append(f"segment sealing in flight failed ({exc}); sealed later")

    def reset(self) -> None:
        """Forget the in-memory index (it is reloaded on the next search)."""
        if self.segmented is not None:
            self.segmented.wait()
        self.flat.reset()
        self.segmented = None
