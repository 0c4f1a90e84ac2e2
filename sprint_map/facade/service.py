"""MapService: the plumbing of a :class:`~sprint_map.map.SprintMap` that the service and the
fleet need, reached as :attr:`SprintMap.service <sprint_map.map.SprintMap.service>`.

The user's verbs (create, ingest, localize, remove, join, ...) are the facade's own; what is
here drives them from outside one call: a drive committed as it streams in
(:meth:`MapService.begin_drive`, the server's sessions), a drive localised by a farm's worker
and committed by the writer (:meth:`MapService.prepare_ingest`,
:meth:`MapService.commit_prepared`), the views, caches, centring and GNSS aid a localizer is
made of (:class:`~sprint_map.facade.supply.MapSupply`), and the index retrained beside the
commits (the service's writer thread). One service per map.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Container, Iterable, Sequence
from contextlib import AbstractContextManager
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from sprint_map.facade.supply import MapSupply
from sprint_map.frontend.centring import DriveCentring
from sprint_map.merge.commit import DriveWriter, IngestResult
from sprint_map.merge.rule import select_merges
from sprint_map.storage.group_writer import GroupWriter
from sprint_map.storage.records import SequenceRecord
from sprint_map.storage.sequence_writer import SequenceWriter
from sprint_map.util.arrays import DescriptorsLike, Float64Array

if TYPE_CHECKING:  # imported where used: reading a map needs no HMM
    from sprint_map.config import MapConfig
    from sprint_map.hmm.config import HMMConfig
    from sprint_map.localize.localizer import FrameDecision
    from sprint_map.merge.join import DriveLocalisation, JoiningMap
    from sprint_map.merge.prepared import PreparedDrive

    class ServedMap(JoiningMap, Protocol):
        """What the service API uses of its map (:class:`sprint_map.map.SprintMap` is one)."""

        @property
        def config(self) -> MapConfig: ...

        def sequences(self) -> list[SequenceRecord]: ...

        def positions(self, seq_id: int) -> Float64Array | None: ...

        def ingest(self, descriptors: Any, name: str | None = None,
                   positions: np.ndarray | None = None, *, merge: bool = True,
                   hmm: HMMConfig | None = None, source: str = "") -> IngestResult: ...

__all__ = ["MapService"]


class MapService(MapSupply):
    """The service API of one map (see the module docstring): made by the map, one per map.
    What a localizer is made of (view, cache, centring, GNSS aid) is :class:`MapSupply`'s.

    Parameters
    ----------
    smap : ServedMap
        The map it serves (:class:`~sprint_map.map.SprintMap`).
    """

    map: ServedMap

    def __init__(self, smap: ServedMap) -> None:
        super().__init__(smap)

    # --- committing -------------------------------------------------------------------------
    def begin_drive(self, name: str | None = None, source: str = "",
                    reserved: Container[str] = (), centring: DriveCentring | None = None
                    ) -> DriveWriter:
        """Start committing a localised drive: append its rows, then
        :meth:`~sprint_map.merge.commit.DriveWriter.commit` it with its decisions (the one commit
        path of ``ingest``, ``merge``, ``commit_prepared`` and the service; see
        :mod:`sprint_map.merge.commit`). One drive at a time per writer.

        Parameters
        ----------
        name : str, optional
            The sequence's name, checked now, before any row is written; without one it is
            ``seq-<id>`` (or ``seq-<id>-2``, ...), avoiding the map's names and ``reserved``.
        source : str
            Where the drive came from (kept with the sequence).
        reserved : container of str
            Names a default name must avoid too (the service's open sessions).
        centring : DriveCentring, optional
            Rows are stored centred by a fresh one like it (the prior the drive was localised
            with); default :meth:`drive_centring`.

        Returns
        -------
        DriveWriter
            A context manager: ``append`` the rows, then ``commit``.

        Raises
        ------
        ReadOnlyMapError
            The map is open read-only.
        DuplicateNameError
            A sequence of the map already has ``name``.
        InputError
            ``name`` is not a valid name (not UTF-8 text, too long, ...).

        Examples
        --------
        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> road = np.random.default_rng(0).standard_normal((30, 16)).astype(np.float32)
        >>> with example_map(dim=16) as m:
        ...     with m.service.begin_drive("monday") as drive:
        ...         _ = drive.append(road)
        ...         done = drive.commit([], None)  # no decision: appended as it is
        ...     print(done.added.sequence.name, m.stats()["vertices"])
        monday 30
        """
        config = self.map.config
        return DriveWriter(SequenceWriter(self.store, name, source, reserved),
                           config.merge, config.merge.both_ways,
                           self.store.component_of, config.admission,
                           centring.fresh() if centring is not None else self.drive_centring())

    def prepare_ingest(self, batches: Iterable[DescriptorsLike], *, merge: bool = True,
                       hmm: HMMConfig | None = None) -> PreparedDrive:
        """Localise a drive as :meth:`SprintMap.ingest <sprint_map.map.SprintMap.ingest>`
        would, against one snapshot, without committing (read-only is enough): an ingest
        farm's workers do this in parallel (:mod:`sprint_map.merge.prepared`).

        Parameters
        ----------
        batches : iterable of array_like
            The drive's search batches, (n, dim) each, as ``ingest`` would get them.
        merge : bool
            False: the drive will be appended as it is (nothing is localised).
        hmm : HMMConfig, optional
            Model parameters for this drive; default the map's own.

        Returns
        -------
        PreparedDrive
            The decisions, timing and snapshot for :meth:`commit_prepared`.

        Raises
        ------
        DescriptorShapeError
            A batch whose dimension is not the map's.
        InvalidDescriptorError
            A batch holding NaN or infinite values.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map({"monday": 30}, dim=16) as m:
        ...     road = m.descriptors(0)
        ...     prepared = m.service.prepare_ingest([road])  # a farm's worker, read-only
        ...     print(len(prepared.decisions), m.stats()["sequences"])
        30 1
        """
        from sprint_map.merge.prepared import prepare_drive

        return prepare_drive(self.map, batches, merge=merge, hmm=hmm)

    def commit_prepared(self, prepared: PreparedDrive, batches: Sequence[DescriptorsLike],
                        name: str | None = None, positions: np.ndarray | None = None, *,
                        hmm: HMMConfig | None = None, source: str = ""
                        ) -> tuple[IngestResult, str | None]:
        """Commit a drive :meth:`prepare_ingest` localised, with the result ``ingest`` would
        give now: if drives committed since its snapshot could have changed its localisation
        it is localised again first.

        Parameters
        ----------
        prepared : PreparedDrive
            What :meth:`prepare_ingest` returned.
        batches : sequence of array_like
            The same batches, as described.
        name, positions, hmm, source
            As for :meth:`SprintMap.ingest <sprint_map.map.SprintMap.ingest>`.

        Returns
        -------
        tuple of (IngestResult, str or None)
            The result, and why the drive was re-localised (None: its prepared decisions
            were committed).

        Raises
        ------
        ReadOnlyMapError
            The map is open read-only.
        DuplicateNameError
            A sequence of the map already has ``name``.

        Notes
        -----
        The staleness check costs O(N * M * dim) for the M vertices committed since the
        snapshot (:func:`sprint_map.merge.prepared.stale_reason`).

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map({"monday": 30}, dim=16) as m:
        ...     road = m.descriptors(0)
        ...     prepared = m.service.prepare_ingest([road])
        ...     result, why = m.service.commit_prepared(prepared, [road], "tuesday")
        ...     print(result.added.sequence.name, why, result.merged.sum())
        tuesday None 30
        """
        from sprint_map.merge.prepared import stale_reason

        centring = prepared.centring if prepared.centring is not None else self.drive_centring()
        reason = stale_reason(self.map, prepared,
                              centring.fresh().apply(np.concatenate(list(batches))))
        if reason is not None:
            return self.map.ingest(iter(batches), name, positions, merge=prepared.merge,
                                   hmm=hmm, source=source), reason
        with self.begin_drive(name, source, centring=centring) as drive:
            for batch in batches:
                drive.append(batch)
            done = drive.commit(prepared.decisions, positions)
        return done.result(prepared.decisions, prepared.timing, drive.name), None

    def localise_for_join(self, source: str | os.PathLike[str], seq_ids: Sequence[int],
                          hmm: HMMConfig | None = None) -> list[DriveLocalisation]:
        """Localise drives ``seq_ids`` of the map at ``source`` against this one (read-only is
        enough) as :meth:`SprintMap.join <sprint_map.map.SprintMap.join>` does, without
        committing: what a farm's task does for a join (:mod:`sprint_map.fleet.join`).

        Parameters
        ----------
        source : str or path
            The map the drives come from (opened read-only).
        seq_ids : sequence of int
            Its drives to localise.
        hmm : HMMConfig, optional
            Model parameters; default the map's own.

        Returns
        -------
        list of DriveLocalisation
            One per drive, in order. Costs what ``ingest``'s localisation costs.

        Raises
        ------
        NotAMapError
            ``source`` holds no map.
        InputError
            ``source`` is this map.
        UnknownSequenceError
            ``source`` has no sequence of one of the ids.
        """
        from sprint_map.merge.join import localise_drive
        from sprint_map.storage.join import open_source_map

        with open_source_map(source, self.store) as src:
            return [localise_drive(self.map, src, src.sequence(i), hmm) for i in seq_ids]

    def select_merges(self, decisions: Sequence[FrameDecision]) -> np.ndarray:
        """The map's merge rule over one drive's decisions (:mod:`sprint_map.merge.rule`,
        with the ``merge_*`` fields of the map's config): which would become edges.

        Parameters
        ----------
        decisions : sequence of FrameDecision
            One drive's decisions, in frame order (usually smoothed).

        Returns
        -------
        numpy.ndarray
            One bool per decision: True where it would be merged.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map({"monday": 30}, dim=16) as m:
        ...     road = m.descriptors(0)
        ...     decisions, _ = m.localize(road, smooth=True)
        ...     print(m.service.select_merges(decisions).sum())
        30
        """
        return select_merges(decisions, self.map.config.merge)

    def group_commit(self) -> AbstractContextManager[None]:
        """Commit several localised drives as a group: each is still its own atomic, durable
        commit, but the index is persisted once, at the end
        (:meth:`sprint_map.storage.store.MapStore.group_commit`).

        Returns
        -------
        context manager
            The group: the drives committed inside it.

        Raises
        ------
        ReadOnlyMapError
            The map is open read-only.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map({"monday": 30}, dim=16) as m:
        ...     road = m.descriptors(0)
        ...     with m.service.group_commit():  # the index persisted once, after both
        ...         _ = m.ingest(road, name="tuesday"), m.ingest(road, name="wednesday")
        ...     print(m.stats()["sequences"], m.stats()["components"])
        3 1
        """
        return self.store.group_commit()

    def begin_group(self) -> GroupWriter:
        """Start a group of drives appended as they are (no localisation) and committed
        together: one fsync of their rows, one LMDB transaction, each drive whole or absent
        (:mod:`sprint_map.storage.group_writer`; ``ingest_drives`` with ``merge=False``).

        Returns
        -------
        GroupWriter
            A context manager: add the drives, then commit.

        Raises
        ------
        ReadOnlyMapError
            The map is open read-only.
        """
        return self.store.begin_group()

    def retrain_index_beside(self, exclusive: Callable[[], AbstractContextManager[object]]
                             ) -> bool:
        """Stop retraining the approximate index inside commits (``index_retrain_growth``)
        and do it here instead, if the map outgrew it: trained while searches go on, switched
        under ``exclusive()``. For a service's writer thread, between commits
        (:meth:`sprint_map.storage.index.map_index.IndexStore.retrain_beside`).

        Parameters
        ----------
        exclusive : callable
            Makes a lock that excludes this process's searches and commits.

        Returns
        -------
        bool
            True if the index was retrained.

        Raises
        ------
        ReadOnlyMapError
            The map is open read-only.
        """
        self.store.defer_index_retraining()
        return self.store.retrain_index_beside(exclusive)
