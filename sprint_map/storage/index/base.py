"""What every kind of retrieval index of a map offers: one interface, one contract.

A retrieval index answers "which committed vertices have the descriptors nearest to these
queries". It is a *cache* of the shards (LMDB and the shards are the truth, vertex id = shard
row): it may lag the map and is caught up from the shards, it must never lead it, and any file
of it the map does not vouch for is dropped and rebuilt. Two kinds implement it:

* :class:`~sprint_map.storage.index.flat.FlatIndex`: exact, one FAISS flat file;
* :class:`~sprint_map.storage.index.segmented.SegmentedIndex`: approximate candidates (PCA,
  IVF-PQ or IVF-SQ8 segments plus an exact tail) re-ranked by exact distance from the shards.

:class:`~sprint_map.storage.index.map_index.IndexStore` holds one of them (the *active* index) and
replaces it by another kind when the map's config and size call for it. Everything it asks of
an index is declared here, with the same signature and the same return types for every kind;
``tests/storage/index_contract.py`` is the one test suite every kind passes.

Life of an index object: constructed *unloaded* (nothing read; only the file-level methods
work), :meth:`~RetrievalIndex.load`-ed (files opened, caught up to the committed vertex count),
kept up to date with :meth:`~RetrievalIndex.catch_up` / :meth:`~RetrievalIndex.add`,
persisted by the writer, and :meth:`~RetrievalIndex.close`-d (unloaded again; idempotent).
Costs below use N for the committed vertices, d for the dimension, q for the queries.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from sprint_map.storage.index.projection import Projection
from sprint_map.storage.shards import ShardSet
from sprint_map.storage.store_config import StoreConfig
from sprint_map.util.arrays import Descriptors, SearchResult

__all__ = ["CHUNK", "PAD_DISTANCE", "IndexNotLoadedError", "RetrievalIndex", "padded_results"]

#: Rows read from the shards per batch when catching up or rebuilding.
CHUNK = 65536
#: The distance of a padding hit (id -1, fewer than k hits): FAISS's ``FLT_MAX``.
PAD_DISTANCE = np.finfo(np.float32).max


class IndexNotLoadedError(RuntimeError):
    """An operation that needs the in-memory index was called before :meth:`load`."""


def padded_results(n_queries: int, k: int) -> SearchResult:
    """The answer to ``n_queries`` queries with no hit: distances ``PAD_DISTANCE`` (float32),
    ids -1 (int64), both of shape ``(n_queries, k)``."""
    return (np.full((n_queries, k), PAD_DISTANCE, dtype=np.float32),
            np.full((n_queries, k), -1, dtype=np.int64))


class RetrievalIndex(ABC):
    """A retrieval index over the committed descriptors of one map (abstract).

    Parameters
    ----------
    directory : Path
        The ``index/`` directory its files live in (shared by every kind: each kind's file
        names are its own).
    config : StoreConfig
        The map's config (dimension, and the kind's parameters).
    writable : bool
        Whether this process may write or delete files (the map's writer).
    events : list of str, optional
        Where loading reports what it had to do (files discarded, rebuilt); shared with the
        caller, which shows them in ``check`` and ``info``.
    projection : Projection, optional
        The map's learned projection (:mod:`~sprint_map.storage.index.projection`): rows and
        queries are given raw and searched projected (``config.dim`` is then its output
        dimension); distances are squared L2 in the projected space.
    """

    #: Short name of the kind (``describe()["type"]`` says more).
    kind: ClassVar[str]
    #: Whether searches return the true nearest neighbours (else approximate candidates).
    exact: ClassVar[bool]
    #: What this kind's published files are called in reports ("the segments").
    files: ClassVar[str]

    def __init__(self, directory: Path, config: StoreConfig, *, writable: bool,
                 events: list[str] | None = None, projection: Projection | None = None
                 ) -> None:
        self.directory = directory
        self.projection = projection
        self.config = config
        self.dim = config.dim
        self.writable = writable
        self.events: list[str] = events if events is not None else []
        #: The shards the index was loaded from (and re-ranks from); None until loaded.
        self.shards: ShardSet | None = None

    # --- state -------------------------------------------------------------------------------
    @property
    @abstractmethod
    def loaded(self) -> bool:
        """Whether the in-memory index exists (:meth:`load` ran, :meth:`close` did not). O(1)."""

    @property
    @abstractmethod
    def covered(self) -> int:
        """Vertices ``0..covered-1`` the in-memory index holds (0 unloaded). O(1)."""

    @property
    @abstractmethod
    def persisted(self) -> int:
        """Vertices the trusted files this object loaded or wrote cover (0 unloaded). O(1)."""

    @abstractmethod
    def persisted_on_disk(self) -> int:
        """Vertices the published files cover, without loading them. O(files) ``stat``s or
        one small file read."""

    @abstractmethod
    def has_files(self) -> bool:
        """Whether any file of this kind is in the directory (trusted or not). O(files)."""

    @abstractmethod
    def published(self) -> bool:
        """Whether this kind has a usable publication a reader would open. O(files)."""

    @abstractmethod
    def describe(self) -> dict[str, Any]:
        """What ``info`` reports: at least ``"type"`` (a str); loaded or not. O(1) reads."""

    def project(self, rows: Descriptors) -> Descriptors:
        """``rows`` (raw descriptors) in the searched space: projected if the map learned a
        projection, else as they are (C-contiguous float32). O(len(rows) * dim_in * dim)."""
        if self.projection is None:
            return np.ascontiguousarray(rows, dtype=np.float32)
        return self.projection.apply(rows)

    def require_loaded(self) -> ShardSet:
        """The shards of the loaded index; :class:`IndexNotLoadedError` if not loaded."""
        if not self.loaded or self.shards is None:
            raise IndexNotLoadedError(f"the {self.kind} index is not loaded: load() first")
        return self.shards

    # --- opening -----------------------------------------------------------------------------
    @abstractmethod
    def discard_untrusted(self, committed: int) -> list[str]:
        """Delete this kind's files the map (``committed`` vertices) does not vouch for: ahead
        of it, torn, or not named by the publication (the writer's open). Returns what was
        done, one line each. O(files) ``stat``s: no file is read whole."""

    @abstractmethod
    def load(self, committed: int, shards: ShardSet) -> bool:
        """Open the trusted files and catch up to ``committed`` vertices from ``shards``.

        Loaded already: only catches up. Returns False (and stays unloaded) when this kind
        cannot be built from what is published and the shards alone (an approximate index
        with no usable trained model); an exact index always loads (from the shards if need
        be, an event saying so).

        Notes
        -----
        O(bytes of the trusted files) plus :meth:`catch_up`.
        """

    def catch_up(self, committed: int, shards: ShardSet) -> None:
        """Add shard rows ``covered..committed-1`` (:meth:`add`, ``CHUNK`` rows at a time).

        Notes
        -----
        O((committed - covered) * d) reads of the shards' memory maps plus :meth:`add`.
        """
        self.require_loaded()
        self.shards = shards
        start = self.covered
        while start < committed:
            stop = min(committed, start + CHUNK)
            self.add(start, shards.rows(start, stop, committed))
            start = stop

    def outdated(self) -> bool:
        """Whether this (reader's) index lags the published files so far that reopening them
        beats catching up from the shards. O(1); never for an exact index."""
        return False

    # --- reading -----------------------------------------------------------------------------
    @abstractmethod
    def search(self, queries: Descriptors, k: int) -> SearchResult:
        """The ``k`` nearest covered vertices of each query row.

        Parameters
        ----------
        queries : ndarray, shape (q, d)
            Query descriptors (converted to C-contiguous float32).
        k : int
            Hits per query (>= 1); more than the index holds is allowed.

        Returns
        -------
        distances : ndarray of float32, shape (q, k)
            Exact squared L2 distances, ascending in each row; ``PAD_DISTANCE`` for padding.
        ids : ndarray of int64, shape (q, k)
            Vertex ids in ``0..covered-1``, distinct in a row; -1 for padding (at the end).

        Raises
        ------
        IndexNotLoadedError
            Before :meth:`load`.
        """

    # --- writing -----------------------------------------------------------------------------
    @abstractmethod
    def add(self, start: int, rows: Descriptors) -> None:
        """Add ``rows`` as vertices ``start..start+len(rows)-1`` (``start`` must be
        :attr:`covered`; ValueError otherwise). The rows must be those vertices' committed
        shard rows: an approximate index re-ranks its candidates from the shards.

        Raises
        ------
        IndexNotLoadedError
            Before :meth:`load`.
        """

    @abstractmethod
    def after_commit(self, committed: int, shards: ShardSet) -> bool:
        """Called by the writer once the index (if loaded) covers a commit up to
        ``committed``: schedule persisting. True if the caller should :meth:`persist` now."""

    @abstractmethod
    def persist(self) -> bool:
        """Publish (atomically) what the files do not cover yet; True if files changed.
        A reader's or an unloaded index: False."""

    @abstractmethod
    def rebuild(self, committed: int, shards: ShardSet) -> None:
        """Build the index of ``committed`` vertices afresh from the shards and publish it in
        place of this kind's files (a kill leaves the old publication or the new one). The
        writer only; leaves the index loaded.

        Notes
        -----
        O(committed * d) to read the shards and write the files (plus training, for an
        approximate index).
        """

    def merge(self) -> bool:
        """Merge the published pieces into one (``compact``); False if nothing to merge."""
        return False

    @abstractmethod
    def remove_files(self) -> list[str]:
        """Delete every file of this kind (another kind superseded it); returns their names.
        The in-memory index, if any, is not touched. O(files)."""

    # --- lifetime ----------------------------------------------------------------------------
    @abstractmethod
    def close(self) -> None:
        """Finish background work and forget the in-memory index (unloaded again: ``load``
        may reopen it). Idempotent. A background job's ``OSError`` is raised once (only its
        unpublished work is lost)."""
