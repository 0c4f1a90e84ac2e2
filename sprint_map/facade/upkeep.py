"""MapUpkeep: how :class:`~sprint_map.map.SprintMap` forgets and keeps its map: drives
removed or unmerged, the space of removed drives reclaimed (compact), redundant views dropped
(summarize), the retrieval index rebuilt or given a learned projection.

A mixin of the facade over its store (:class:`~sprint_map.storage.store.MapStore`): each
change is one atomic commit, or a new generation selected atomically, and needs a map open
for writing (:class:`~sprint_map.errors.ReadOnlyMapError` otherwise).
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

from sprint_map.facade.reading import MapReading
from sprint_map.storage.records import CompactReport, RemoveResult, UnmergeResult

if TYPE_CHECKING:
    pass

__all__ = ["MapUpkeep"]


class MapUpkeep(MapReading):
    """The facade's upkeep (see the module docstring) over ``store``."""

    def sequence_id(self, seq: int | str) -> int:
        """The id of sequence ``seq``.

        Parameters
        ----------
        seq : int or str
            An id (returned as it is) or a name, checked by the store's name rules.

        Returns
        -------
        int
            The sequence's id.

        Raises
        ------
        UnknownSequenceError
            No sequence has that name (one no sequence can have, like ``""``, included).
        InputError
            A name that is not UTF-8 text.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map({"monday": 10}, dim=16) as m:
        ...     print(m.sequence_id("monday"), m.sequence_id(0))
        0 0
        """
        return seq if isinstance(seq, int) else self.store.sequence_by_name(seq).seq_id

    def remove_sequences(self, sequences: Iterable[int | str]) -> RemoveResult:
        """Forget whole drives, in one atomic commit: the sequences, every edge to or from them
        and their positions; the components they held together split where the remaining
        edges no longer connect them. Their descriptors stay on disk (never returned by a
        search) until :meth:`compact`. Nothing is removed if one of them does not exist.

        Parameters
        ----------
        sequences : iterable of int or str
            Sequence ids (``int``) or names (``str``).

        Returns
        -------
        RemoveResult
            The sequences, vertices and edges removed.

        Raises
        ------
        UnknownSequenceError
            No sequence with that id or name (an empty name included).
        InputError
            A name that is not UTF-8 text.
        ReadOnlyMapError
            The map is open read-only.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map({"monday": 10, "tue": 10}, dim=16) as m:
        ...     removed = m.remove_sequences(["monday"])
        ...     print([s.name for s in m.sequences()], m.info()["removed_vertices"])
        ['tue'] 10
        """
        ids = [self.sequence_id(s) for s in sequences]
        return self.store.remove_sequences(ids)

    def unmerge(self, seq: int | str) -> UnmergeResult:
        """Undo a drive's merge: revoke every edge sequence ``seq`` added, in one atomic commit
        (both directions, with their reverse index), and rebuild the components they held
        together. The sequence stays in the map, as do the edges later drives added to it
        (:meth:`remove_sequences` drops those too). Unmerging a drive that added no edge (or
        twice) changes nothing (:func:`sprint_map.storage.provenance.unmerge_sequence`).

        Parameters
        ----------
        seq : int or str
            The drive's id or name.

        Returns
        -------
        UnmergeResult
            The edges revoked and the components split.

        Raises
        ------
        UnknownSequenceError
            No sequence with that id or name.
        ReadOnlyMapError
            The map is open read-only.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map({"monday": 40}, dim=16) as m:
        ...     road = m.descriptors(0)
        ...     _ = m.ingest(road, name="tuesday")
        ...     _ = m.unmerge("tuesday")
        ...     print(m.edges(added_by="tuesday"), m.stats()["components"])
        [] 2
        """
        return self.store.unmerge(self.sequence_id(seq))

    # --- maintenance ------------------------------------------------------------------------
    def compact(self) -> CompactReport:
        """Reclaim the space of removed sequences: shards, index and LMDB are rewritten into a
        new generation (vertex ids renumbered densely, sequence ids kept) and selected
        atomically; a kill at any point leaves the old or the new map
        (:func:`sprint_map.storage.compaction.compact_map`).

        Returns
        -------
        CompactReport
            The vertices and bytes before and after.

        Raises
        ------
        ReadOnlyMapError
            The map is open read-only.
        StorageIOError
            The new generation could not be written (the old one stays selected).

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map({"monday": 10, "tue": 10}, dim=16) as m:
        ...     _ = m.remove_sequences(["monday"])
        ...     report = m.compact()
        ...     print(report.vertices_before, report.vertices_after, m.info()["removed_vertices"])
        20 10 0
        """
        return self.store.compact()

    def summarize(self, per_place: int = 1) -> dict[str, Any]:
        """Drop the views a place already has, as a new generation selected atomically (like
        :meth:`compact`, which it also does): :mod:`sprint_map.merge.summary` says what is
        redundant, :mod:`sprint_map.storage.reduction` how the rest is written.

        Parameters
        ----------
        per_place : int
            Alike views kept per place and appearance, at most.

        Returns
        -------
        dict
            ``vertices_before``, ``vertices_after``, ``sequences_before``, ``sequences_after``,
            ``stitches``, ``sightings``, ``bytes_before``, ``bytes_after`` and ``seconds``.

        Raises
        ------
        ValueError
            ``per_place`` below 1.
        ReadOnlyMapError
            The map is open read-only.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map({"monday": 20}, dim=16) as m:
        ...     report = m.summarize()
        ...     print(report["vertices_before"], report["vertices_after"] <= 20)
        20 True
        """
        from sprint_map.merge.summary import plan_summary

        started = time.monotonic()
        plan = plan_summary(self.store, per_place, self.config.admission)
        report = self.store.summarize(plan.reduction)
        return {**plan.to_dict(), "bytes_before": report.bytes_before,
                "bytes_after": report.bytes_after,
                "seconds": round(time.monotonic() - started, 3)}

    def rebuild_index(self, *, train: bool = False) -> list[str]:
        """Rebuild the retrieval index from the shards (``sprint-map index``); readers keep
        using the old index until the new one is published atomically
        (:meth:`sprint_map.storage.index.map_index.IndexStore.train`).

        Parameters
        ----------
        train : bool
            Also retrain the approximate index's PCA and quantizer on a fresh sample.

        Returns
        -------
        list of str
            What was rebuilt, one line each.

        Raises
        ------
        ReadOnlyMapError
            The map is open read-only.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map({"monday": 20}, dim=16) as m:
        ...     road = m.descriptors(0)
        ...     _ = m.rebuild_index()
        ...     print(m.search(road[:1], 1)[1].tolist())
        [[0]]
        """
        return self.store.rebuild_index(train=train)

    def learn(self) -> dict[str, Any]:
        """Learn a descriptor projection from the map's merged edges and rebuild the index
        with it if it retrieves held-back pairs better (``sprint-map index --learn``); crash
        safe like a rebuild (:mod:`sprint_map.storage.learning`).

        Returns
        -------
        dict
            ``{pairs, dim_in, dim_out, adopted, heldout_recall_before, heldout_recall_after}``.

        Raises
        ------
        ReadOnlyMapError
            The map is open read-only.
        """
        report = self.store.learn().to_dict()
        report.pop("reason")
        return report

    def unlearn(self) -> bool:
        """Drop the learned projection and search the plain descriptor again
        (``sprint-map index --no-learn``).

        Returns
        -------
        bool
            False if the map had none.

        Raises
        ------
        ReadOnlyMapError
            The map is open read-only.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map(dim=16) as m:
        ...     print(m.unlearn())
        False
        """
        return self.store.unlearn()
