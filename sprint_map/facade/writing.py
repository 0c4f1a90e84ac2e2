"""MapWriting: how :class:`~sprint_map.map.SprintMap` adds drives to its map: as they are, or
localised and merged (ingest, merge), several in groups, or joined from another map. Removing,
unmerging and the map's upkeep are :class:`~sprint_map.facade.upkeep.MapUpkeep`'s.

A mixin of the facade over its store (:class:`~sprint_map.storage.store.MapStore`); every
change is one atomic commit (or a new generation selected atomically), and needs a map open
for writing (:class:`~sprint_map.errors.ReadOnlyMapError` otherwise). The commits of a drive
go through the map's service API (:attr:`SprintMap.service <sprint_map.map.SprintMap.service>`).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Sequence
from contextlib import AbstractContextManager
from typing import TYPE_CHECKING, Any

import numpy as np

from sprint_map.facade.core import stored_config
from sprint_map.facade.localizing import MapLocalizing
from sprint_map.facade.upkeep import MapUpkeep
from sprint_map.hmm.config import HMMConfig
from sprint_map.merge.commit import IngestResult
from sprint_map.merge.drives import DEFAULT_GROUP_DRIVES, Drive, ingest_drives
from sprint_map.storage.records import (
    AddResult,
    EdgeSpec,
)
from sprint_map.util.arrays import DescriptorsLike

if TYPE_CHECKING:
    from sprint_map.localize.localizer import FrameDecision, Localizer
    from sprint_map.merge.join import JoinResult, LocaliseMany

__all__ = ["MapWriting"]


class MapWriting(MapUpkeep, MapLocalizing):
    """The facade's changes (see the module docstring) over ``store``."""

    # --- drives -----------------------------------------------------------------------------
    def add_sequence(
        self,
        descriptors: Any,
        name: str | None = None,
        positions: np.ndarray | None = None,
        edges: Sequence[EdgeSpec] = (),
        source: str = "",
        thumbnails: Sequence[bytes] | None = None,
    ) -> AddResult:
        """Append a sequence as it is (no localisation) with optional edges and thumbnails,
        atomically (:meth:`sprint_map.storage.store.MapStore.add_sequence`).

        Parameters
        ----------
        descriptors : array_like, shape (N, dim)
            One descriptor per frame.
        name : str, optional
            A name no sequence of the map has (default ``seq-<id>``).
        positions : array_like, shape (N, 2..4), optional
            Per-frame ``x, y[, heading_deg[, timestamp]]``.
        edges : sequence of EdgeSpec
            Edges to earlier sequences, committed with it.
        source : str
            Free text: where the sequence came from.
        thumbnails : sequence of bytes, optional
            One small JPEG per frame.

        Returns
        -------
        AddResult
            The new sequence's record, its component and the edges added.

        Raises
        ------
        DescriptorShapeError
            ``descriptors`` are not (N, dim).
        InvalidDescriptorError
            They hold NaN or infinite values.
        EmptySequenceError
            No frame.
        DuplicateNameError
            A sequence already has ``name``.
        ReadOnlyMapError
            The map is open read-only.

        Examples
        --------
        >>> import tempfile, numpy as np
        >>> from sprint_map import MapConfig, SprintMap
        >>> road = np.random.default_rng(0).standard_normal((30, 16)).astype(np.float32)
        >>> with SprintMap.create(tempfile.mkdtemp() + "/city.map", MapConfig(dim=16)) as m:
        ...     added = m.add_sequence(road, name="monday")
        ...     print(added.sequence.name, added.sequence.length, m.stats()["vertices"])
        monday 30 30
        """
        centring = self.service.drive_centring()
        rows = centring.apply(descriptors)
        return self.store.add_sequence(
            rows, name=name, positions=positions, edges=edges, source=source,
            thumbnails=thumbnails, stats=(centring.stats.frames, centring.stats.mean),
        )

    def ingest(
        self,
        descriptors: DescriptorsLike | Iterable[DescriptorsLike],
        name: str | None = None,
        positions: np.ndarray | None = None,
        *,
        merge: bool = True,
        hmm: HMMConfig | None = None,
        source: str = "",
        observe: Callable[[Localizer], None] | None = None,
        thumbnails: Sequence[bytes] | None = None,
        fixes: np.ndarray | None = None,
    ) -> IngestResult:
        """Localise a drive against the map, then commit it with its decisions as edges.

        Every frame is localised causally, batch by batch; once the drive has been seen whole,
        the after-drive pipeline (:func:`sprint_map.merge.smoothing.smoothed_decisions`) re-makes
        its decisions and the merge rule (:mod:`sprint_map.merge.rule`) selects the edges. The
        sequence, its edges and the union-find merges are committed in one transaction. With
        ``merge=False``, or on an empty map, the drive is appended as it is.

        Parameters
        ----------
        descriptors : array_like or iterable of array_like
            An (N, dim) array or an iterable of batches, streamed: each batch is localised and
            written to the shards (uncommitted) as it arrives.
        name, positions, source
            As for :meth:`add_sequence`.
        merge : bool
            False: append the drive as it is.
        hmm : HMMConfig, optional
            Model parameters for this drive; default the map's own.
        observe : callable, optional
            Receives the localizer before the first frame (e.g.
            :meth:`sprint_map.localize.trace.TraceRecorder.attach`).
        thumbnails : sequence of bytes, optional
            One JPEG per frame (read after the batches), committed with the drive; they let
            the merge verify refused runs on the images.
        fixes : numpy.ndarray, optional
            (N, 2 or 3): the drive's GNSS fixes ``x, y[, sigma_m]`` (NaN rows: none) in the
            frame of the map's positions; where the map stores positions they weigh
            localisation and veto far merges (:mod:`sprint_map.localize.gnss`).

        Returns
        -------
        IngestResult
            The committed sequence (``added``), the decisions, which were merged and timing.

        Raises
        ------
        DescriptorShapeError, InvalidDescriptorError, EmptySequenceError
            Descriptors that do not fit the map (nothing is committed).
        DuplicateNameError
            A sequence already has ``name``.
        InputError
            ``fixes`` not one per frame or out of range.
        ReadOnlyMapError
            The map is open read-only.

        Notes
        -----
        Per frame: one k-NN search (batched), one HMM step over the active set and the
        pipeline's passes, O(live) each; O(k) hits and the sparse forward belief kept per frame
        until the drive ends; about 2 KiB of thumbnail per frame.

        Examples
        --------
        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> rng = np.random.default_rng(0)
        >>> road = rng.standard_normal((40, 16)).astype(np.float32)
        >>> with example_map(dim=16) as m:
        ...     first = m.ingest(road, name="monday")  # an empty map: appended as it is
        ...     again = m.ingest(road + 0.01 * rng.standard_normal((40, 16)), name="tuesday")
        ...     print(again.added.sequence.name, m.stats()["components"])
        tuesday 1
        """
        from sprint_map.localize.localizer import SEARCH_BATCH, Localizer, Timing

        service = self.service
        batches: Iterable[DescriptorsLike]
        if isinstance(descriptors, np.ndarray):
            batches = (descriptors[i : i + SEARCH_BATCH]
                       for i in range(0, len(descriptors), SEARCH_BATCH))
        else:
            batches = descriptors
        n = len(descriptors) if isinstance(descriptors, np.ndarray) else None
        localizer = (Localizer(self, hmm, record=True, gnss=service.gnss_aid(fixes, n))
                     if merge and self.stats()["vertices"] else None)
        if localizer is None and fixes is not None:
            service.gnss_aid(fixes, n, index=False)  # checked all the same
        if localizer is not None and observe is not None:
            observe(localizer)
        centring = localizer.centring if localizer is not None else None
        with service.begin_drive(name, source, centring=centring) as drive:
            for batch in batches:
                if localizer is not None:  # it centres the batch as the drive stores it
                    for _ in localizer.iter_localize(iter([batch])):
                        pass
                drive.append(batch)
            if fixes is not None and n is None:  # streamed: the drive's length known now
                service.gnss_aid(fixes, drive.frames, index=False)
            decisions = (self.smoothed(localizer, thumbnails=thumbnails)
                         if localizer is not None else [])
            done = drive.commit(decisions, positions, thumbnails=thumbnails)
        return done.result(decisions, localizer.timing if localizer else Timing(), drive.name)

    def ingest_drives(
        self,
        drives: Sequence[Drive],
        *,
        merge: bool = True,
        hmm: HMMConfig | None = None,
        group_drives: int = DEFAULT_GROUP_DRIVES,
        on_committed: Callable[[list[IngestResult]], Any] | None = None,
        observe: Callable[[Localizer], None] | None = None,
    ) -> list[IngestResult]:
        """Ingest several drives in order, each its own sequence, as :meth:`ingest` one after
        the other would (each localised against the map holding the earlier ones), committed
        in groups (:func:`sprint_map.merge.drives.ingest_drives`: errors, costs).

        Parameters
        ----------
        drives : sequence of Drive
            The drives, in order.
        merge, hmm, observe
            As for :meth:`ingest` (``observe`` is called for each drive).
        group_drives : int
            Drives per group: with ``merge=False`` one transaction a group, each drive whole or
            absent; localised, one index persist a group.
        on_committed : callable, optional
            Called with each group's results once it is committed.

        Returns
        -------
        list of IngestResult
            One per drive, in order.

        Raises
        ------
        InputError
            ``group_drives`` below 1, or two drives of the call with one name.
        DuplicateNameError, DescriptorShapeError
            As for :meth:`ingest` (the groups before are committed).

        Examples
        --------
        >>> import numpy as np
        >>> from sprint_map import Drive
        >>> from sprint_map.examples import example_map
        >>> rows = np.random.default_rng(0).standard_normal((2, 20, 16)).astype(np.float32)
        >>> with example_map(dim=16) as m:
        ...     done = m.ingest_drives([Drive(rows[0], "a"), Drive(rows[1], "b")], merge=False)
        ...     print([r.added.sequence.name for r in done])
        ['a', 'b']
        """
        return ingest_drives(self, drives, merge=merge, hmm=hmm, group_drives=group_drives,
                             on_committed=on_committed, observe=observe)

    def merge(self, descriptors: Any, decisions: Sequence[FrameDecision], name: str | None = None,
              positions: np.ndarray | None = None, source: str = "") -> AddResult | None:
        """Commit a localised drive with the decisions the merge rule selects as edges,
        atomically.

        Parameters
        ----------
        descriptors : array_like, shape (N, dim)
            The drive's descriptors.
        decisions : sequence of FrameDecision
            One per frame: usually :meth:`localize` with ``smooth=True``.
        name, positions, source
            As for :meth:`add_sequence`.

        Returns
        -------
        AddResult or None
            None when the map's admission stored no frame of it (its sightings were committed).

        Raises
        ------
        DescriptorShapeError, InvalidDescriptorError
            Descriptors that do not fit the map.
        DuplicateNameError
            A sequence already has ``name``.
        ReadOnlyMapError
            The map is open read-only.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map({"monday": 30}, dim=16) as m:
        ...     road = m.descriptors(0)
        ...     decisions, _ = m.localize(road, smooth=True)
        ...     print(m.merge(road, decisions, name="again").sequence.name)
        again
        """
        with self.service.begin_drive(name, source) as drive:
            return drive.commit(decisions, positions, rows=descriptors).added

    def join(self, source: str | os.PathLike[str], *, drives: Sequence[str] | None = None,
             prefix: str = "", merge: bool = True, require_connected: bool = False,
             hmm: HMMConfig | None = None, localise_many: LocaliseMany | None = None,
             progress: Callable[[int], None] | None = None,
             exclusive: Callable[[], AbstractContextManager[Any]] | None = None,
             on_commit: Callable[[set[int]], None] | None = None) -> JoinResult:
        """Bring drives of the map at ``source`` into this one with everything they carry,
        then localise each against what this map held before and merge its confident
        decisions as ``ingest`` would, in one atomic commit (:mod:`sprint_map.merge.join`).
        ``source`` is opened read-only and never written; a writer is kept out of it meanwhile.
        A drive this map already holds (same content digest) is not copied again.

        Parameters
        ----------
        source : str or path
            The other map.
        drives : sequence of str, optional
            Names of its drives to bring (default: all).
        prefix : str
            Prepended to their names (to resolve clashes).
        merge : bool
            False: only copy.
        require_connected : bool
            Refuse a join that leaves an imported drive with no path to this map's drives.
        hmm : HMMConfig, optional
            Model parameters; default the map's own.
        localise_many : callable, optional
            Localise several drives elsewhere (:func:`sprint_map.fleet.farm.farm_localise_join`).
        progress : callable, optional
            Called with the rows done since its last call.
        exclusive, on_commit : callable, optional
            A service's map gate and component registry, around the commit only.

        Returns
        -------
        JoinResult
            The drives joined, skipped and the edges merged.

        Raises
        ------
        InputError
            ``source`` is this map.
        MapLockedError
            A writer is at work on ``source``.
        IncompatibleMapError, UnknownSequenceError, DuplicateNameError, UnconnectedJoinError
            Refused before anything is written (both maps unchanged).

        Examples
        --------
        >>> import tempfile, numpy as np
        >>> from sprint_map import MapConfig, SprintMap
        >>> rng, folder = np.random.default_rng(0), tempfile.mkdtemp()
        >>> road = rng.standard_normal((30, 16)).astype(np.float32)
        >>> with SprintMap.create(folder + "/a.map", MapConfig(dim=16)) as a:
        ...     _ = a.add_sequence(road, name="monday")
        >>> with SprintMap.create(folder + "/b.map", MapConfig(dim=16)) as b:
        ...     _ = b.add_sequence(road + 0.01 * rng.standard_normal((30, 16)), name="tuesday")
        ...     joined = b.join(folder + "/a.map")
        ...     print(joined.vertices_copied, [s.name for s in b.sequences()])
        ...     print(b.stats()["components"])
        30 ['tuesday', 'monday']
        1
        """
        from sprint_map.merge.join import join_maps
        from sprint_map.storage.join import open_source_map

        with open_source_map(source, self.store, stored_config) as src:
            configs = (self.config.to_dict(), stored_config(src.config_record).to_dict())
            return join_maps(self, src, configs, drives=drives, prefix=prefix, merge=merge,
                             require_connected=require_connected, hmm=hmm,
                             localise_many=localise_many, progress=progress,
                             exclusive=exclusive, on_commit=on_commit)
