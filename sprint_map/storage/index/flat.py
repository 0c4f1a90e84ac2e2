"""The exact flat FAISS index of a map: a cache of the shards, persisted atomically and stamped.

The index file is ``index/flat.<upto>.faiss`` where ``upto`` is the number of vertices it covers
(vertex ids ``0..upto-1``; FAISS id = vertex id). Because LMDB is the source of truth, the index
may lag it (the missing tail is re-added from the shards when the index is loaded) but never
lead it: a file stamped beyond the committed vertex count (LMDB lost or never made the commit) is
discarded and the index rebuilt from the shards. So is a file whose size is not the size its
stamp implies (cut short, or garbage appended): one ``stat``, no read.

Loading is lazy: opening a map does not read the index; the first search does.
"""

from __future__ import annotations

import errno
import re
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sprint_map.storage.index.base import IndexNotLoadedError, RetrievalIndex
from sprint_map.storage.index.model import use_threads
from sprint_map.storage.index.projection import Projection
from sprint_map.storage.shards import ShardSet
from sprint_map.storage.store_config import StoreConfig
from sprint_map.testing.crash import crash_point
from sprint_map.util import atomic
from sprint_map.util.arrays import Descriptors, SearchResult
from sprint_map.util.atomic import fsync_dir, publish
from sprint_map.util.exact_search import ExactFlat

if TYPE_CHECKING:
    import faiss
else:  # imported on first use: commands that only read LMDB never load it
    from sprint_map.util.lazy import faiss

__all__ = ["FlatIndex", "file_bytes", "file_problem", "index_files"]

INDEX_RE = re.compile(r"^flat\.(\d{12})\.faiss$")


def index_files(directory: Path) -> list[tuple[int, Path]]:
    """Persisted index files as ``(upto, path)``, ascending."""
    found = []
    if directory.is_dir():
        for entry in directory.iterdir():
            match = INDEX_RE.match(entry.name)
            if match:
                found.append((int(match.group(1)), entry))
    return sorted(found)


@cache
def _header_bytes(dim: int) -> int:
    return len(faiss.serialize_index(faiss.IndexIDMap2(faiss.IndexFlatL2(dim))))


def file_bytes(dim: int, upto: int) -> int:
    """Size of the file :meth:`IndexStore.persist` writes for ``upto`` vectors of ``dim``.

    A flat index stores each vector (``4 * dim`` bytes) and its id (8 bytes) after a header
    of fixed size, so the size is exact and checking it catches a torn or padded file.
    """
    return _header_bytes(dim) + upto * (4 * dim + 8)


def file_problem(path: Path, upto: int, committed: int, dim: int) -> str | None:
    """Why the index file ``path`` stamped ``upto`` cannot be trusted, or None. One ``stat``.

    The reason reads after "is": ``f"{path.name} is {reason}"``.
    """
    if upto > committed:
        return f"ahead of the map ({committed} vertices)"
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        return "gone (removed meanwhile)"
    want = file_bytes(dim, upto)
    if size != want:
        return f"torn: {size} bytes, {upto} vectors of dim {dim} take {want}"
    return None


def _ids_dense(index: faiss.Index, upto: int) -> bool:
    """Whether ``index`` holds ids ``0..upto-1`` in order, as every persisted file does.
    O(upto)."""
    if not hasattr(index, "id_map"):
        return True  # no ids stored: positions are the ids
    return bool(np.array_equal(faiss.vector_to_array(index.id_map), np.arange(upto)))


class FlatIndex(RetrievalIndex):
    """Exact L2 retrieval over all committed descriptors, as ``IndexIDMap2(IndexFlatL2)``.

    A :class:`~sprint_map.storage.index.base.RetrievalIndex` (see there for the
    parameters and the contract). Its file is rewritten whole on every persist, on a
    geometric schedule (:meth:`after_commit`).
    """

    kind = "flat"
    exact = True
    files = "the flat file"

    def __init__(self, directory: Path, config: StoreConfig, *, writable: bool,
                 events: list[str] | None = None, projection: Projection | None = None
                 ) -> None:
        super().__init__(directory, config, writable=writable, events=events,
                         projection=projection)
        self.index: faiss.IndexIDMap2 | None = None
        self._exact: ExactFlat | None = None  # the certified search over self.index
        self._persisted = 0  # vertices covered by the newest file on disk that we trust

    # --- state -------------------------------------------------------------------------------
    @property
    def loaded(self) -> bool:
        return self.index is not None

    @property
    def covered(self) -> int:
        return 0 if self.index is None else int(self.index.ntotal)

    @property
    def persisted(self) -> int:
        return self._persisted

    @persisted.setter
    def persisted(self, value: int) -> None:
        """Forget (0) or set what the trusted file covers: the next persist rewrites it."""
        self._persisted = value

    def persisted_on_disk(self) -> int:
        """Vertices covered by the newest index file on disk (without loading it). One
        directory listing."""
        files = index_files(self.directory)
        return files[-1][0] if files else 0

    def has_files(self) -> bool:
        return bool(index_files(self.directory))

    def published(self) -> bool:
        return self.has_files()

    def describe(self) -> dict[str, Any]:
        return {"type": "IndexIDMap2(IndexFlatL2)"}

    # --- opening -----------------------------------------------------------------------------
    def discard_untrusted(self, committed: int) -> list[str]:
        """Delete index files ahead of ``committed`` vertices or torn (writer, at open).

        A file ahead saw commits LMDB no longer has; left in place, it would be trusted again
        as soon as new, different commits bring the vertex count up to its stamp. A torn file
        (its size is not what its stamp implies) would only fail to load later.

        Notes
        -----
        One ``stat`` per index file (normally one file): O(1) in the map size.
        """
        actions = []
        for upto, path in index_files(self.directory):
            problem = file_problem(path, upto, committed, self.dim)
            if problem is not None:
                path.unlink(missing_ok=True)
                actions.append(f"removed index {path.name}: {problem}")
        if actions:
            fsync_dir(self.directory)
        return actions

    def _empty(self) -> faiss.IndexIDMap2:
        return faiss.IndexIDMap2(faiss.IndexFlatL2(self.dim))

    def load(self, committed: int, shards: ShardSet) -> bool:
        """Load the newest trustworthy file and bring it up to ``committed`` vertices.

        A file whose vector count, dimension or ids are not the ones its stamp implies is
        discarded (the writer deletes it) and the index rebuilt from the shards. Always True.

        Notes
        -----
        O(file size) to read plus O((committed - upto) * dim) to catch up from the shards.
        """
        if self.index is not None:
            self.catch_up(committed, shards)
            return True
        index = None
        for upto, path in reversed(index_files(self.directory)):
            problem = file_problem(path, upto, committed, self.dim)
            if problem is not None:
                self.events.append(f"index {path.name} is {problem}; discarded")
                if self.writable:
                    path.unlink(missing_ok=True)
                continue
            try:
                candidate = faiss.read_index(str(path))
            except RuntimeError as exc:
                self.events.append(f"index {path.name} unreadable ({exc}); discarded")
                if self.writable:
                    path.unlink(missing_ok=True)
                continue
            if candidate.ntotal != upto or candidate.d != self.dim or not _ids_dense(
                    candidate, upto):
                # A garbled id would be a vertex outside the map: a cache event, not a crash.
                self.events.append(f"index {path.name} does not match its stamp; discarded")
                if self.writable:
                    path.unlink(missing_ok=True)
                continue
            index = faiss.IndexIDMap2(candidate) if not isinstance(
                candidate, faiss.IndexIDMap2
            ) else candidate
            self._persisted = upto
            break
        self.index = index if index is not None else self._empty()
        self.shards = shards
        if index is None and committed:
            self.events.append(f"index rebuilt from the shards ({committed} vertices)")
        self.catch_up(committed, shards)
        return True

    # --- reading -----------------------------------------------------------------------------
    def search(self, queries: Descriptors, k: int) -> SearchResult:
        """k nearest vertices of each query row: ``(distances, vertex_ids)``, -1 padded.

        Exact and independent of the batch: a query gets the same ids and distances, bit for
        bit, searched alone or among others (:func:`~sprint_map.util.exact_search.
        certified_search`: FAISS for candidates, each re-measured by a function of the two
        vectors alone, ties ordered by vertex id).

        Notes
        -----
        O(q * covered * d) (brute force; every core for a batch of 8 or more queries), plus
        O(q * (k + 8) * d) to certify.
        """
        if self.index is None:
            raise IndexNotLoadedError("the flat index is not loaded: load() first")
        queries = self.project(queries)  # float64 rounded: a query alone or in a batch alike
        use_threads(len(queries))
        if self._exact is None or self._exact.index is not self.index:
            self._exact = ExactFlat(self.index)
        return self._exact.search(queries, k)

    # --- writing -----------------------------------------------------------------------------
    def add(self, start: int, rows: Descriptors) -> None:
        """Add ``rows`` as vertex ids ``start..`` (must continue the covered range).
        O(len(rows) * d)."""
        if self.index is None:
            raise IndexNotLoadedError("the flat index is not loaded: load() first")
        if start != self.covered:
            raise ValueError(f"index covers {self.covered} vertices, cannot add at {start}")
        ids = np.arange(start, start + len(rows), dtype=np.int64)
        self.index.add_with_ids(self.project(rows), ids)

    def after_commit(self, committed: int, shards: ShardSet) -> bool:
        """Due when the map outgrew the file by ``index_persist_every`` vertices and by
        ``index_persist_growth`` times the file's size (the file is rewritten whole on every
        persist, so the interval grows with it: total bytes written stay O(final size), not
        O(size^2 / interval)). Loads the index when due. O(1) but for that load."""
        on_disk = self._persisted if self.index is not None else self.persisted_on_disk()
        cfg = self.config
        due = committed - on_disk >= max(cfg.index_persist_every,
                                         cfg.index_persist_growth * on_disk)
        if due and self.index is None:
            self.load(committed, shards)
        return due

    def persist(self) -> bool:
        """Publish the in-memory index atomically if it covers more than the file on disk.

        Notes
        -----
        O(covered * d) written (the whole file), then older files removed.
        """
        index = self.index
        if not self.writable or index is None or self.covered <= self._persisted:
            return False
        upto = self.covered
        path = self.directory / f"flat.{upto:012d}.faiss"

        def write(partial: Path) -> None:
            try:
                faiss.write_index(index, str(partial))
            except RuntimeError as exc:
                # FAISS reports I/O failures (ENOSPC, EIO) as RuntimeError; as an OSError,
                # publish() removes the partial file and raises StorageIOError.
                raise OSError(errno.EIO, str(exc)) from exc
            crash_point("index.partial_written")

        # FAISS reports a failed write only on stderr: the size tells (see atomic.publish).
        publish(path, write, expected_size=file_bytes(self.dim, upto))
        crash_point("index.published")
        for older, old_path in index_files(self.directory):
            if older != upto:
                old_path.unlink(missing_ok=True)
        fsync_dir(self.directory)
        self._persisted = upto
        return True

    def rebuild(self, committed: int, shards: ShardSet) -> None:
        """Rebuild the index from the shards and publish it in place of every index file.

        Notes
        -----
        O(committed * dim) to read the shards and write the file, published atomically
        (:meth:`persist`): a kill leaves the old files or the new one, never a torn one.
        """
        assert self.writable
        self.index = self._empty()
        self._persisted = 0
        self.shards = shards
        self.catch_up(committed, shards)
        if not self.persist():  # an empty map: no file at all
            self.remove_files()

    def remove_files(self) -> list[str]:
        removed = []
        for _, path in index_files(self.directory):
            atomic.unlink(path)
            removed.append(path.name)
        if removed:
            fsync_dir(self.directory)
        return removed

    # --- lifetime ----------------------------------------------------------------------------
    def close(self) -> None:
        """Forget the in-memory index (it is reloaded on the next search). Idempotent."""
        self.index = None
        self._persisted = 0
        self.shards = None
