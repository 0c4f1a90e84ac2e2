"""MapSearch: the facade's k-NN search over the map's descriptor index: all live rows, one
sequence's range, the index's segments, and the search threads' cap.

A mixin of :class:`~sprint_map.facade.reading.MapReading` over the map's store; each search reads
the committed rows (removed sequences' filtered out) with exact distances. The examples build a
small map in a temporary directory.
"""

from __future__ import annotations

from sprint_map.facade.core import MapCore
from sprint_map.storage.index.model import cap_threads
from sprint_map.util.arrays import DescriptorsLike, SearchResult

__all__ = ["MapSearch"]


class MapSearch(MapCore):
    """The facade's k-NN search (see the module docstring) over ``store``."""

    def search(self, queries: DescriptorsLike, k: int) -> SearchResult:
        """k-NN over all live committed descriptors (removed sequences' filtered out), with
        exact distances (the approximate index re-ranks its candidates on the true rows).
        ``queries`` are in the map's space: a drive's descriptors pass through
        :meth:`~sprint_map.facade.service.MapService.drive_centring` first. O(vertices * dim) a query
        with the exact index; the approximate one scans O(sqrt(vertices)) codes.

        Parameters
        ----------
        queries : array_like, shape (q, dim)
            Query descriptors (converted to float32).
        k : int
            Hits per query; more than the map holds is allowed (padded).

        Returns
        -------
        distances : ndarray of float32, shape (q, k)
            Exact squared L2 distances, ascending in each row (padding: float32's largest).
        ids : ndarray of int64, shape (q, k)
            Vertex ids (:meth:`locate` names their frames); -1 for padding, at the end.

        Raises
        ------
        DescriptorShapeError
            ``queries`` not numeric, not 2-D, or not of the map's dimension.
        EmptySequenceError
            No query row.
        InvalidDescriptorError
            A query holding NaN or Inf.
        MapCorruptError, StorageIOError
            A damaged map; LMDB, a shard or the index cannot be read.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> smap = example_map({"mon": 6})
        >>> rows = smap.descriptors(0)
        >>> distances, ids = smap.search(rows[[3]] + 0.01, 8)
        >>> smap.locate([ids[0, 0]]), ids[0, -2:].tolist()  # frame 3 first; 2 hits of padding
        ([(0, 3)], [-1, -1])
        >>> float(distances[0, 0]) < 0.01
        True
        >>> smap.search(rows[3], 1)
        Traceback (most recent call last):
            ...
        sprint_map.errors.DescriptorShapeError: descriptors must be a 2-D array (N x 8), got (8,)
        >>> smap.close()
        """
        return self.store.search(queries, k)

    def search_within(self, queries: DescriptorsLike, k: int, start: int,
                      stop: int | None = None) -> SearchResult:
        """:meth:`search` among vertex ids ``[start, stop)`` only, on the map's approximate
        index: what a retrieval shard of the fleet answers (its range: whole segments,
        :meth:`index_segments`). O(the index segments holding ids of the range).

        Parameters
        ----------
        queries : array_like, shape (q, dim)
            Query descriptors, as for :meth:`search`.
        k : int
            Hits per query.
        start : int
            The first vertex id of the range.
        stop : int, optional
            One past its last (None: to the last committed vertex).

        Returns
        -------
        distances, ids : ndarray, shape (q, k)
            As :meth:`search` gives them, every id in the range.

        Raises
        ------
        ValueError
            The map's index is exact (``flat``, or ``auto`` while the map is small).
        DescriptorShapeError, EmptySequenceError, InvalidDescriptorError
            Queries refused, as by :meth:`search`.
        MapCorruptError, StorageIOError
            A damaged map; LMDB, a shard or the index cannot be read.

        Examples
        --------
        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> smap = example_map({"mon": 5})
        >>> smap.search_within(np.ones((1, 8)), 2, 0)
        Traceback (most recent call last):
            ...
        ValueError: a search within a vertex range needs the approximate index; this map's ...
        >>> smap.close()
        """
        return self.store.search_within(queries, k, start, stop)

    def index_segments(self) -> list[tuple[int, int]]:
        """Vertex ranges of the approximate index's sealed segments: where retrieval shards
        cut the map (:mod:`sprint_map.fleet.shards`). O(segments) once the index is loaded
        (loading it catches it up with the shards first).

        Returns
        -------
        list of (int, int)
            ``(start, stop)`` of each sealed segment, in order; none while the index is
            exact or before its first segment is sealed.

        Raises
        ------
        MapCorruptError, StorageIOError
            A damaged map; LMDB, a shard or the index cannot be read.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> smap = example_map({"mon": 5})
        >>> smap.index_segments()  # a small map's index is exact
        []
        >>> smap.close()
        """
        return self.store.index_segments()

    @staticmethod
    def cap_search_threads(n: int) -> None:
        """Use at most ``n`` OpenMP threads for the searches of the calling thread from now on
        (any map; e.g. the service's batch searcher, whose other core answers HTTP). O(1).

        Parameters
        ----------
        n : int
            The most threads; values below 1 count as 1.

        Returns
        -------
        None

        Examples
        --------
        >>> from sprint_map import SprintMap
        >>> SprintMap.cap_search_threads(1)  # this thread's searches: one thread each
        """
        cap_threads(n)
