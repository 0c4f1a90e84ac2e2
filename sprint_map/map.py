"""SprintMap: the library's front door, composing the store, retrieval and the HMM.

The CLI is a thin layer over this class; everything it does can be done from Python::

    from sprint_map import MapConfig, SprintMap

    with SprintMap.create("city.map", MapConfig(dim=256)) as m:
        m.add_sequence(descriptors, name="monday")
    with SprintMap.open("city.map", readonly=True) as m:
        print(m.info())
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Container, Iterable, Sequence
from contextlib import AbstractContextManager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sprint_map.config import MapConfig
from sprint_map.errors import (
    DescriptorShapeError,
    InputError,
)
from sprint_map.frontend.centring import CentringStats, DriveCentring
from sprint_map.hmm.config import HMMConfig
from sprint_map.map_reading import MapReading
from sprint_map.merge.commit import DriveWriter, IngestResult
from sprint_map.merge.drives import DEFAULT_GROUP_DRIVES, Drive, ingest_drives
from sprint_map.merge.rule import select_merges
from sprint_map.storage.generation import current_data
from sprint_map.storage.group_writer import GroupWriter
from sprint_map.storage.provenance import list_edges
from sprint_map.storage.records import (
    AddResult,
    CheckReport,
    CompactReport,
    EdgeInfo,
    EdgeSpec,
    RemoveResult,
    RepairReport,
    UnmergeResult,
)
from sprint_map.storage.sequence_writer import SequenceWriter
from sprint_map.storage.store import MapStore
from sprint_map.storage.store_config import decode_stored_config
from sprint_map.util import dataclass_dict
from sprint_map.util.arrays import DescriptorsLike, Float64Array
from sprint_map.util.validation import decode_text

if TYPE_CHECKING:  # imported where used: ``info`` and ``sequences`` need no HMM and no OpenCV
    from sprint_map.frontend.bags import BagOptions
    from sprint_map.frontend.sources import FrameSource, ProgressCallback
    from sprint_map.hmm.cache import ComponentCache
    from sprint_map.localize.gnss import GnssAid, PositionIndex
    from sprint_map.localize.localizer import FrameDecision, Localizer, MapView, Timing
    from sprint_map.merge.join import DriveLocalisation, JoinResult, LocaliseMany
    from sprint_map.merge.prepared import PreparedDrive


__all__ = ["SprintMap", "stored_config"]


def stored_config(record: dict[str, Any]) -> MapConfig:
    """The configuration a map stores (its meta record, decoded JSON), or MapCorruptError if
    it is not a valid config (:func:`~sprint_map.storage.store_config.decode_stored_config`).
    The store checks its own fields of it when it opens
    (:func:`sprint_map.storage.store.decode_config`); this checks the rest. A record without
    ``centring`` is a map made before centring: its rows are stored as given, so it reads as
    ``centring={"mode": "none"}``. O(fields).
    """
    if isinstance(record, dict) and "centring" not in record:
        record = {**record, "centring": {"mode": "none"}}
    return decode_stored_config(MapConfig.from_dict, record)


class SprintMap(MapReading):
    """A persistent place-recognition map.

    Open with :meth:`create` or :meth:`open`, preferably as a context manager; one process at a
    time may open a map for writing, any number for reading (each sees consistent snapshots).
    Its reads (sequences, vertices, descriptors, positions, thumbnails, exports, search) are
    :class:`~sprint_map.map_reading.MapReading`'s.
    """

    def __init__(self, store: MapStore) -> None:
        self.store = store
        self._config = stored_config(store.config_record)
        #: positions read so far (seq_id -> (first vertex, rows)) and the index of a snapshot
        self._placed: dict[int, tuple[int, Float64Array]] = {}
        self._position_index: tuple[tuple[Any, ...], PositionIndex] | None = None
        #: the pooled condition prior and the map counts it was pooled at
        self._prior: tuple[tuple[int, int], CentringStats | None] | None = None

    # --- lifecycle --------------------------------------------------------------------------
    @classmethod
    def create(cls, path: str | os.PathLike[str], config: MapConfig) -> SprintMap:
        """Create an empty map in ``path`` (absent or empty) and open it for writing.

        Raises
        ------
        InputError
            ``path`` is not UTF-8 text (nothing is created).
        """
        return cls(MapStore.create(path, config))

    @classmethod
    def open(cls, path: str | os.PathLike[str], *, readonly: bool = False) -> SprintMap:
        """Open an existing map; a writer recovers interrupted writes first.

        Notes
        -----
        O(1) in the size of the map: reads the meta record, and for a writer truncates the one
        shard that may hold uncommitted rows. Raises ``MapLockedError`` at once if another
        process is writing.
        """
        return cls(MapStore.open(path, readonly=readonly, check_config=stored_config))

    def close(self) -> None:
        """Persist the index (writer) and release the map."""
        self.store.close()

    def flush(self) -> None:
        """Persist the index now (it is a cache; LMDB is already durable)."""
        self.store.flush()

    def group_commit(self) -> AbstractContextManager[None]:
        """Commit several localised drives as a group: each is still its own atomic, durable
        commit, but the index is persisted once, at the end (see
        :meth:`sprint_map.storage.store.MapStore.group_commit`)."""
        return self.store.group_commit()

    def begin_group(self) -> GroupWriter:
        """Start a group of drives appended as they are (no localisation) and committed
        together: one fsync of their rows, one LMDB transaction, each drive whole or absent
        (see :mod:`sprint_map.storage.group_writer`; ``ingest_drives`` with ``merge=False``
        uses it)."""
        return self.store.begin_group()

    def __enter__(self) -> SprintMap:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def path(self) -> Path:
        return self.store.path

    @property
    def config(self) -> MapConfig:
        return self._config

    @property
    def readonly(self) -> bool:
        return self.store.readonly

    @property
    def closed(self) -> bool:
        """Whether :meth:`close` was called (nothing can be read any more)."""
        return self.store.env is None

    def is_current(self) -> bool:
        """Whether the generation this map opened is still the live one: False once a
        ``compact`` selected a new copy (a reader then sees no later commit: reopen the map).
        O(1): reads the small ``CURRENT`` file."""
        return current_data(self.path) == self.store.data_path

    @property
    def warnings(self) -> list[str]:
        """Problems that failed no call and lost nothing (e.g. the index cache not saved)."""
        return self.store.warnings

    # --- writing ----------------------------------------------------------------------------
    def add_sequence(
        self,
        descriptors: Any,
        name: str | None = None,
        positions: np.ndarray | None = None,
        edges: Sequence[EdgeSpec] = (),
        source: str = "",
        thumbnails: Sequence[bytes] | None = None,
    ) -> AddResult:
        """Append a sequence as it is (no localisation) with optional edges and thumbnails
        (one JPEG per frame), atomically.

        See :meth:`sprint_map.storage.store.MapStore.add_sequence`.
        """
        centring = self.drive_centring()
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

        Every frame is localised causally, batch by batch; once the drive has been seen whole, the
        after-drive pipeline (:func:`sprint_map.merge.smoothing.smoothed_decisions`) re-makes its
        decisions and the merge rule (:mod:`sprint_map.merge.rule`) selects the edges. The sequence,
        its edges and the union-find merges are committed in one transaction. With ``merge=False``,
        or on an empty map, the drive is appended as it is.

        ``descriptors`` is an (N, dim) array or an iterable of batches, streamed: each batch is
        localised and written to the shards (uncommitted) as it arrives. ``thumbnails``, one JPEG
        per frame (read after the batches), are committed with the drive and let the merge verify
        refused runs on the images. ``observe`` receives the localizer before the first frame (e.g.
        :meth:`sprint_map.localize.trace.TraceRecorder.attach`). ``fixes`` (N, 2 or 3): the
        drive's GNSS fixes ``x, y[, sigma_m]`` (NaN rows: none) in the frame of the map's
        positions; where the map stores positions they weigh localisation and veto far merges
        (:mod:`sprint_map.localize.gnss`).

        Notes
        -----
        Per frame: one k-NN search (batched), one HMM step over the active set and the pipeline's
        passes, O(live) each; O(k) hits and the sparse forward belief kept per frame until the drive
        ends; about 2 KiB of thumbnail per frame.
        """
        from sprint_map.localize.localizer import SEARCH_BATCH, Localizer, Timing

        batches: Iterable[DescriptorsLike]
        if isinstance(descriptors, np.ndarray):
            batches = (descriptors[i : i + SEARCH_BATCH]
                       for i in range(0, len(descriptors), SEARCH_BATCH))
        else:
            batches = descriptors
        n = len(descriptors) if isinstance(descriptors, np.ndarray) else None
        localizer = (Localizer(self, hmm, record=True, gnss=self.gnss_aid(fixes, n))
                     if merge and self.stats()["vertices"] else None)
        if localizer is None and fixes is not None:
            self.gnss_aid(fixes, n, index=False)  # checked all the same
        if localizer is not None and observe is not None:
            observe(localizer)
        centring = localizer.centring if localizer is not None else None
        with self.begin_drive(name, source, centring=centring) as drive:
            for batch in batches:
                if localizer is not None:  # it centres the batch as the drive stores it
                    for _ in localizer.iter_localize(iter([batch])):
                        pass
                drive.append(batch)
            if fixes is not None and n is None:  # streamed: the drive's length known now
                self.gnss_aid(fixes, drive.frames, index=False)
            decisions = (self.smoothed(localizer, thumbnails=thumbnails)
                         if localizer is not None else [])
            done = drive.commit(decisions, positions, thumbnails=thumbnails)
        return done.result(decisions, localizer.timing if localizer else Timing(), drive.name)

    def begin_drive(self, name: str | None = None, source: str = "",
                    reserved: Container[str] = (), centring: DriveCentring | None = None
                    ) -> DriveWriter:
        """Start committing a localised drive: append its rows, then
        :meth:`~sprint_map.merge.commit.DriveWriter.commit` it with its decisions (the one commit
        path of ``ingest``, ``merge``, ``commit_prepared`` and the service; see
        :mod:`sprint_map.merge.commit`).

        ``name`` is checked now, before any row is written; without one the sequence is named
        ``seq-<id>`` (or ``seq-<id>-2``, ...), avoiding the map's names and ``reserved``. One
        drive at a time per writer. Rows are appended as described and stored centred by
        ``centring`` (a fresh one like it: the prior the drive was localised with), by default
        :meth:`drive_centring`.
        """
        return DriveWriter(SequenceWriter(self.store, name, source, reserved),
                           self.config.merge, self.config.merge.both_ways,
                           self.store.component_of, self.config.admission,
                           centring.fresh() if centring is not None else self.drive_centring())

    def drive_centring(self) -> DriveCentring:
        """A new drive's centring (:mod:`sprint_map.frontend.centring`, ``config.centring``):
        every drive's descriptors pass through one, in drive order, before they are searched
        or stored, so that the map answers by place, not by condition. Its prior is the map's
        mean condition now (:meth:`condition_prior`).

        Notes
        -----
        O(dim), or O(sequences * dim) the first time after a commit (the prior is pooled
        again from the drives' statistics).
        """
        return DriveCentring(self.config.centring, self.config.dim, self.condition_prior())

    def condition_prior(self) -> CentringStats | None:
        """The map's mean condition: the frame-weighted mean of its drives' statistics
        (:meth:`drive_stats`), or None for a map without any. Cached until the map changes.
        O(sequences * dim) when pooled."""
        if not self.config.centring.enabled or not self.config.centring.prior_frames:
            return None
        counts = self.store.stats()
        key = (counts["sequences"], counts["vertices"])
        if self._prior is None or self._prior[0] != key:
            pooled = CentringStats.pool(CentringStats(frames, mean)
                                        for _, frames, mean in self.store.all_drive_stats())
            self._prior = (key, pooled)
        return self._prior[1]

    def prepare_ingest(self, batches: Iterable[DescriptorsLike], *, merge: bool = True,
                       hmm: HMMConfig | None = None) -> PreparedDrive:
        """Localise a drive as :meth:`ingest` would, against one snapshot, without committing
        (read-only is enough): an ingest farm's workers do this in parallel. ``batches`` are
        the drive's search batches (as ``ingest`` would get them). See
        :mod:`sprint_map.merge.prepared`."""
        from sprint_map.merge.prepared import prepare_drive

        return prepare_drive(self, batches, merge=merge, hmm=hmm)

    def commit_prepared(self, prepared: PreparedDrive, batches: Sequence[DescriptorsLike],
                        name: str | None = None, positions: np.ndarray | None = None, *,
                        hmm: HMMConfig | None = None, source: str = ""
                        ) -> tuple[IngestResult, str | None]:
        """Commit a drive :meth:`prepare_ingest` localised, with the result :meth:`ingest`
        would give now: if drives committed since its snapshot could have changed its
        localisation it is localised again first (``ingest``). Returns the result and why it
        was re-localised (None: its prepared decisions were committed).

        Notes
        -----
        The staleness check costs O(N * M * dim) for the M vertices committed since the
        snapshot (:func:`sprint_map.merge.prepared.stale_reason`).
        """
        from sprint_map.merge.prepared import stale_reason

        centring = prepared.centring if prepared.centring is not None else self.drive_centring()
        reason = stale_reason(self, prepared,
                              centring.fresh().apply(np.concatenate(list(batches))))
        if reason is not None:
            return self.ingest(iter(batches), name, positions, merge=prepared.merge, hmm=hmm,
                               source=source), reason
        with self.begin_drive(name, source, centring=centring) as drive:
            for batch in batches:
                drive.append(batch)
            done = drive.commit(prepared.decisions, positions)
        return done.result(prepared.decisions, prepared.timing, drive.name), None

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
        in groups of ``group_drives`` (appended with ``merge=False``: one transaction a group,
        each drive whole or absent).

        See :func:`sprint_map.merge.drives.ingest_drives` (errors, costs, ``on_committed``).
        """
        return ingest_drives(self, drives, merge=merge, hmm=hmm, group_drives=group_drives,
                             on_committed=on_committed, observe=observe)

    def join(self, source: str | os.PathLike[str], *, drives: Sequence[str] | None = None,
             prefix: str = "", merge: bool = True, require_connected: bool = False,
             hmm: HMMConfig | None = None, localise_many: LocaliseMany | None = None,
             progress: Callable[[int], None] | None = None,
             exclusive: Callable[[], AbstractContextManager[Any]] | None = None,
             on_commit: Callable[[set[int]], None] | None = None) -> JoinResult:
        """Bring drives of the map at ``source`` into this one with everything they carry,
        then localise each against what this map held before and merge its confident
        decisions as ``ingest`` would (``merge=False``: only copy), in one atomic commit.

        ``drives``: names of the source's drives (default: all); ``prefix``: prepended to their
        names (to resolve clashes); ``require_connected``: refuse a join that leaves an
        imported drive with no path to this map's drives. ``source`` is opened read-only and
        never written; a writer is kept out of it meanwhile. A drive this map already holds
        (same content digest) is not copied again. ``localise_many``: localise several drives
        elsewhere (a Ray farm, :func:`sprint_map.fleet.farm.farm_localise_join`); ``progress``:
        rows done since its last call; ``exclusive``, ``on_commit``: a service's map gate and
        component registry around the commit only (its writer thread,
        :mod:`sprint_map.server.writer`). See :mod:`sprint_map.merge.join`.

        Raises
        ------
        InputError
            ``source`` is this map.
        MapLockedError
            A writer is at work on ``source``.
        IncompatibleMapError, UnknownSequenceError, DuplicateNameError, UnconnectedJoinError
            Refused before anything is written (both maps unchanged).
        """
        from sprint_map.merge.join import join_maps
        from sprint_map.storage.join import open_source_map

        with open_source_map(source, self.store, stored_config) as src:
            configs = (self.config.to_dict(), stored_config(src.config_record).to_dict())
            return join_maps(self, src, configs, drives=drives, prefix=prefix, merge=merge,
                             require_connected=require_connected, hmm=hmm,
                             localise_many=localise_many, progress=progress,
                             exclusive=exclusive, on_commit=on_commit)

    def localise_for_join(self, source: str | os.PathLike[str], seq_ids: Sequence[int],
                          hmm: HMMConfig | None = None) -> list[DriveLocalisation]:
        """Localise drives ``seq_ids`` of the map at ``source`` against this one (read-only is
        enough) as :meth:`join` does, without committing: what a farm's task does for a join
        (:mod:`sprint_map.fleet.join`). Costs what ``ingest``'s localisation costs."""
        from sprint_map.merge.join import localise_drive
        from sprint_map.storage.join import open_source_map

        with open_source_map(source, self.store) as src:
            return [localise_drive(self, src, src.sequence(i), hmm) for i in seq_ids]

    def select_merges(self, decisions: Sequence[FrameDecision]) -> np.ndarray:
        """The map's merge rule over one drive's decisions: which would become edges.

        See :mod:`sprint_map.merge.rule`; the rule's parameters are the ``merge_*`` fields of
        the map's config.
        """
        return select_merges(decisions, self.config.merge)

    def merge(self, descriptors: Any, decisions: Sequence[FrameDecision], name: str | None = None,
              positions: np.ndarray | None = None, source: str = "") -> AddResult | None:
        """Commit a localised drive with the decisions the merge rule selects as edges,
        atomically (``decisions``: usually :meth:`localize` with ``smooth=True``). None when the
        map's admission stored no frame of it (its sightings were committed)."""
        with self.begin_drive(name, source) as drive:
            return drive.commit(decisions, positions, rows=descriptors).added

    def remove_sequences(self, sequences: Iterable[int | str]) -> RemoveResult:
        """Forget whole drives: each ``int`` is a sequence id, each ``str`` a sequence name.

        One atomic commit removes the sequences, every edge to or from them and their
        positions, and splits the components they held together where the remaining edges no
        longer connect them. Their descriptors stay on disk (never returned by a search) until
        :meth:`compact`. Nothing is removed if one of them does not exist.

        Raises
        ------
        UnknownSequenceError
            No sequence with that id or name (an empty name included).
        InputError
            A name that is not UTF-8 text.
        """
        ids = [self._seq_id(s) for s in sequences]
        return self.store.remove_sequences(ids)

    def unmerge(self, seq: int | str) -> UnmergeResult:
        """Undo a drive's merge: revoke every edge sequence ``seq`` (id or name) added.

        One atomic commit removes those edges (both directions, with their reverse index) and
        rebuilds the components they held together, which split where no other edge joins
        them. The sequence stays in the map, as do the edges later drives added to it (remove
        it with :meth:`remove_sequences` to drop those too). Unmerging a drive that added no
        edge (or twice) changes nothing and reports 0. See
        :func:`sprint_map.storage.provenance.unmerge_sequence`.

        Raises
        ------
        UnknownSequenceError
            No sequence with that id or name.
        """
        return self.store.unmerge(self._seq_id(seq))

    def _seq_id(self, seq: int | str) -> int:
        """The id of sequence ``seq`` (an id, or a name checked by the store's name rules: one
        no sequence can have, like ``""``, is unknown; one that is not UTF-8 an InputError)."""
        return seq if isinstance(seq, int) else self.store.sequence_by_name(seq).seq_id

    def compact(self) -> CompactReport:
        """Reclaim the space of removed sequences: shards, index and LMDB are rewritten into a
        new generation (vertex ids renumbered densely, sequence ids kept) and selected
        atomically. A kill at any point leaves the old or the new map. See
        :func:`sprint_map.storage.compaction.compact_map`.
        """
        return self.store.compact()

    def summarize(self, per_place: int = 1) -> dict[str, Any]:
        """Drop the views a place already has (at most ``per_place`` alike views kept per place
        and appearance), as a new generation selected atomically (like :meth:`compact`, which
        it also does). Returns ``vertices_before``, ``vertices_after``, ``sequences_before``,
        ``sequences_after``, ``stitches``, ``sightings``, ``bytes_before``, ``bytes_after``
        and ``seconds``. See :mod:`sprint_map.merge.summary` (what is redundant) and
        :mod:`sprint_map.storage.reduction` (how the rest is written).

        Raises
        ------
        ValueError
            ``per_place`` below 1.
        """
        from sprint_map.merge.summary import plan_summary

        started = time.monotonic()
        plan = plan_summary(self.store, per_place, self.config.admission)
        report = self.store.summarize(plan.reduction)
        return {**plan.to_dict(), "bytes_before": report.bytes_before,
                "bytes_after": report.bytes_after,
                "seconds": round(time.monotonic() - started, 3)}

    def rebuild_index(self, *, train: bool = False) -> list[str]:
        """Rebuild the retrieval index from the shards; with ``train`` also retrain the
        approximate index's PCA and quantizer on a fresh sample (``sprint-map index``).

        Readers keep using the old index until the new one is published atomically. See
        :meth:`sprint_map.storage.index.map_index.IndexStore.train`.
        """
        return self.store.rebuild_index(train=train)

    def retrain_index_beside(self, exclusive: Callable[[], AbstractContextManager[object]]
                             ) -> bool:
        """Stop retraining the approximate index inside commits (``index_retrain_growth``)
        and do it here instead, if the map outgrew it: trained while searches go on, switched
        under ``exclusive()`` (a lock that excludes this process's searches and commits). For
        a service's writer thread, between commits; True if the index was retrained. See
        :meth:`sprint_map.storage.index.map_index.IndexStore.retrain_beside`."""
        self.store.defer_index_retraining()
        return self.store.retrain_index_beside(exclusive)

    def learn(self) -> dict[str, Any]:
        """Learn a descriptor projection from the map's merged edges and rebuild the index
        with it if it retrieves held-back pairs better (``sprint-map index --learn``):
        ``{pairs, dim_in, dim_out, adopted, heldout_recall_before, heldout_recall_after}``.
        Crash safe like a rebuild; see :mod:`sprint_map.storage.learning`."""
        report = self.store.learn().to_dict()
        report.pop("reason")
        return report

    def unlearn(self) -> bool:
        """Drop the learned projection and search the plain descriptor again
        (``sprint-map index --no-learn``); False if the map had none."""
        return self.store.unlearn()

    def view(self) -> MapView:
        """A new view of the map for one :class:`~sprint_map.localize.localizer.Localizer` (what it
        reads: k-NN search, vertex locations, components and their edges, from pinned LMDB
        snapshots)."""
        from sprint_map.localize.stored_view import StoredMapView

        return StoredMapView(self.store)

    def shared_cache(self) -> ComponentCache:
        """A thread-safe component cache of the map's ``hmm.cache_budget_bytes``, for
        localizers that run in several threads over this map (``Localizer(..., cache=)``):
        each component is loaded once for all of them."""
        from sprint_map.hmm.cache import SharedComponentCache

        return SharedComponentCache(self.config.hmm.cache_budget_bytes)

    def localizer(self, hmm: HMMConfig | None = None, *, record: bool = False,
                  fixes: np.ndarray | None = None, **overrides: Any) -> Localizer:
        """A streaming :class:`Localizer` for one query sequence (read-only use of the map).

        ``overrides`` replace fields of the HMM config for this query only (e.g. ``k=5``);
        ``record`` keeps each frame's hits for :meth:`smoothed`; ``fixes`` are the drive's
        GNSS fixes (see :meth:`ingest`), frame ``i`` the ``i``-th step.
        """
        from sprint_map.localize.localizer import Localizer

        base = hmm or self.config.hmm
        return Localizer(self, dataclass_dict.replace(base, **overrides) if overrides else base,
                         record=record, gnss=self.gnss_aid(fixes, None))

    def gnss_aid(self, fixes: np.ndarray | None, frames: int | None, *, index: bool = True
                 ) -> GnssAid | None:
        """A drive's GNSS ``fixes`` (see :meth:`ingest`) against the map's positions, or None
        when there are no fixes or the map stores no position (GNSS changes nothing then).
        ``frames`` is the drive's length, if known; ``index=False`` only checks the fixes.

        Raises
        ------
        InputError
            Fixes not one per frame, out of range, or with a ``sigma_m`` <= 0
            (:func:`sprint_map.localize.gnss.validate_fixes`).
        """
        from sprint_map.localize.gnss import GnssAid, validate_fixes

        if fixes is None:
            return None
        checked = validate_fixes(fixes, frames, self.config.gnss.sigma_m)
        if not index:
            return None
        positions = self.position_index()
        return GnssAid(self.config.gnss, positions, checked) if positions.size else None

    def position_index(self) -> PositionIndex:
        """The positions the map stores, by vertex and in a KD-tree, as of now
        (:class:`sprint_map.localize.gnss.PositionIndex`); kept until the map changes.

        Notes
        -----
        O(n log n) for the n placed vertices when the map changed (positions of sequences
        read before are kept: each sequence is read once); O(1) otherwise.
        """
        from sprint_map.localize.gnss import PositionIndex

        stats = self.stats()
        key = (stats["vertices"], stats["sequences"], self.store.removed_vertices(),
               str(self.store.data_path))
        if self._position_index is not None and self._position_index[0] == key:
            return self._position_index[1]
        live = {seq.seq_id: seq for seq in self.sequences()}
        placed = {i: p for i, p in self._placed.items()
                  if i in live and live[i].first_vertex == p[0]}
        for seq_id, seq in live.items():
            if seq_id not in placed:
                rows = self.positions(seq_id)
                placed[seq_id] = (seq.first_vertex, rows if rows is not None
                                  else np.empty((0, 2)))
        self._placed = placed
        index = PositionIndex(stats["vertices"], [p for p in placed.values() if len(p[1])],
                              self.config.gnss.map_sigma_m)
        self._position_index = (key, index)
        return index

    def localize(self, descriptors: Any, *, smooth: bool = False, lag: int = 0,
                 thumbnails: Sequence[bytes] | None = None,
                 observe: Callable[[Localizer], None] | None = None,
                 hmm: HMMConfig | None = None, fixes: np.ndarray | None = None,
                 **overrides: Any) -> tuple[list[FrameDecision], Timing]:
        """Localise a whole query drive without changing the map: the one call behind
        ``localize`` (with or without ``--smooth`` and ``--trace``) and ``eval``.

        ``descriptors`` is an (N, dim) array or an iterable of row batches (streamed; searches
        are batched). Without ``smooth`` the decisions are the causal filter's, as a vehicle gets
        them; with it they are the after-drive pipeline's (:func:`sprint_map.merge.smoothing.
        smoothed_decisions`: what ``ingest`` merges, given the same ``thumbnails``, one JPEG per
        frame). ``observe`` receives the localizer before the first frame (e.g.
        :meth:`TraceRecorder.attach <sprint_map.localize.trace.TraceRecorder.attach>`).
        ``hmm`` and ``overrides`` replace the map's HMM config for this query only.
        ``lag`` (frames) answers each frame once ``lag`` more were seen, from the fixed-lag
        smoothed posterior (:class:`~sprint_map.localize.lagged.LaggedLocalizer`; 0: causal);
        it excludes ``smooth``, ``observe`` and ``fixes`` (:class:`InputError`). ``fixes``
        are the drive's GNSS fixes (see :meth:`ingest`; one per frame, checked).

        Notes
        -----
        Per frame: one k-NN search (batched) and one HMM step over the active set; with
        ``smooth``, the pipeline's passes (O(live) per frame each) and O(k) hits kept per frame;
        with ``lag``, ``lag`` backward steps more per frame.
        """
        if lag:
            from sprint_map.localize.lagged import LaggedLocalizer, validate_lag

            validate_lag(lag, whole_drive=smooth or observe is not None or thumbnails is not None,
                         fixes=fixes is not None)
            base = hmm or self.config.hmm
            lagged = LaggedLocalizer(self, lag, dataclass_dict.replace(base, **overrides)
                                     if overrides else base)
            batches = np.asarray(descriptors) if isinstance(descriptors, np.ndarray | list) \
                else descriptors
            return lagged.localize(batches), lagged.timing
        batches = np.asarray(descriptors) if isinstance(descriptors, np.ndarray | list) \
            else descriptors
        if fixes is not None and isinstance(batches, np.ndarray):
            self.gnss_aid(fixes, len(batches), index=False)
        localizer = self.localizer(hmm, record=smooth, fixes=fixes, **overrides)
        if observe is not None:
            observe(localizer)
        decisions = localizer.localize(batches)
        if fixes is not None:
            self.gnss_aid(fixes, len(decisions), index=False)
        if smooth:
            decisions = self.smoothed(localizer, thumbnails=thumbnails)
        return decisions, localizer.timing

    def smoothed(self, localizer: Any, descriptors: DescriptorsLike | None = None,
                 thumbnails: Sequence[bytes] | None = None) -> list[FrameDecision]:
        """The after-drive decisions of the drive ``localizer`` has seen (made with
        ``record=True``), as :func:`sprint_map.merge.smoothing.smoothed_decisions` makes them;
        a proxy of a localiser in another process (the service's Ray replicas) makes them
        there, through its own ``smoothed(descriptors)``. ``descriptors`` let the deep pass
        search a drive recorded shallower than ``smooth_k`` (the service's sessions)."""
        from sprint_map.localize.localizer import Localizer
        from sprint_map.merge.smoothing import smoothed_decisions

        if not isinstance(localizer, Localizer):
            decisions: list[FrameDecision] = localizer.smoothed(descriptors)
            return decisions
        if descriptors is not None:  # the drive as described, centred as it was localised
            descriptors = localizer.centring.fresh().apply(np.asarray(descriptors))
        return smoothed_decisions(localizer, self, descriptors, thumbnails)

    def open_source(self, path: str | os.PathLike[str], *, stride: int = 1,
                    progress: ProgressCallback | None = None,
                    thumbnails: bool = False, bag: BagOptions | None = None) -> FrameSource:
        """Open images, a video, a ``.npy`` or a ROS bag as descriptors that fit this map.

        With ``thumbnails`` the source also makes a small JPEG of each frame
        (``source.thumbnails``, for :meth:`ingest`); images, video and bags only. ``bag``:
        a bag's topics and ``every_m`` (:mod:`sprint_map.frontend.bags`); a bag's GNSS
        positions are ``source.positions`` (for :meth:`metric_positions`).

        Raises
        ------
        InputError
            Images or video given to a map of precomputed descriptors; a path that is not
            UTF-8 text (OpenCV would crash on it, and it would name the sequence).
        DescriptorShapeError
            A ``.npy`` whose dimension is not the map's.
        """
        spec = self.config.descriptor_spec()
        src = Path(decode_text(os.fspath(path), "source path"))
        if spec is None and src.suffix.lower() != ".npy":
            raise InputError(
                f"{src}: this map holds precomputed descriptors (dim {self.config.dim}); give a "
                ".npy of descriptors, or create the map with --descriptor hog for images/video"
            )
        if thumbnails and spec is None:
            raise InputError(f"{src}: thumbnails need images or video, and this map holds "
                             "precomputed descriptors")
        from sprint_map.frontend.sources import open_source

        source = open_source(src, spec, stride=stride, progress=progress,
                             thumbnails=thumbnails, bag=bag)
        if source.dim != self.config.dim:
            raise DescriptorShapeError(
                f"{src}: descriptors have {source.dim} dimensions, the map has {self.config.dim}"
            )
        if spec is not None and spec.kind == "onnx":
            from sprint_map.frontend.onnx_model import unverified_files

            unverified = unverified_files(spec.params)
            if unverified and not any("weights file" in w for w in self.warnings):
                self.warnings.append(
                    f"the map records the digest of {spec.params['model']} only (made before "
                    f"weights files were): its weights file(s) {', '.join(unverified)} are "
                    "not verified")
        return source

    # --- reading ----------------------------------------------------------------------------
    def edges(self, seq: int | str | None = None, *, added_by: int | str | None = None
              ) -> list[EdgeInfo]:
        """Edges between ``(seq, image)`` endpoints with their provenance (``added_by``: the
        drive whose merge created the edge; ``frame``; ``prob``), in vertex order.

        ``seq`` (id or name) keeps the edges touching that sequence (either end);
        ``added_by`` (id or name) those that drive added, i.e. what :meth:`unmerge` of it
        revokes. See :func:`sprint_map.storage.provenance.list_edges` for the costs.

        Raises
        ------
        UnknownSequenceError
            No sequence with that id or name.
        """
        return list_edges(self.store, None if seq is None else self._seq_id(seq),
                          None if added_by is None else self._seq_id(added_by))

    # --- checking ---------------------------------------------------------------------------
    @staticmethod
    def repair(path: str | os.PathLike[str], *, seed: int = 0) -> RepairReport:
        """Repair the map at ``path`` as far as its own data allows, then check it (``sprint-map
        check --repair``; takes the writer lock). See :func:`sprint_map.storage.repair.repair_map`.
        """
        from sprint_map.frontend.thumbnails import decodes
        from sprint_map.storage.repair import repair_map

        return repair_map(path, seed=seed, check_config=stored_config, thumbnail_decodes=decodes)

    def check(self) -> CheckReport:
        """Verify every on-disk invariant (best on a map opened read-only); every thumbnail
        is decoded (:func:`sprint_map.frontend.thumbnails.decodes`)."""
        from sprint_map.frontend.thumbnails import decodes
        from sprint_map.storage.check import check_map

        return check_map(self.store, thumbnail_decodes=decodes)

    def info(self) -> dict[str, Any]:
        """Summary for ``sprint-map info --json``. O(1) but for the directory walk."""
        stats = self.stats()
        index = self.store.index
        return {
            "schema_version": self.store.schema_version,
            "path": str(self.path),
            "sequences": stats["sequences"],
            "vertices": stats["vertices"],
            "edges": stats["edges"],
            "components": stats["components"],
            "dim": self.config.dim,
            "descriptor": self.config.descriptor,
            "admission": self.config.admission.mode,
            "index": {
                **index.describe(),
                # The index is a cache that catches up from the shards when loaded, so a search
                # always covers every committed vertex; "persisted" is what the file on disk holds.
                "ntotal": index.covered if index.index is not None else stats["vertices"],
                "persisted": index.persisted if index.index is not None
                else index.persisted_on_disk(),
            },
            "projection": self.store.index.learned_state().describe(),
            "disk_bytes": self.store.disk_bytes(),
            "removed_vertices": self.store.removed_vertices(),
            "generation": self.store.data_path.name if self.store.data_path != self.path else "",
            "config": self.config.to_dict(),
        }
