"""MapSupply: what a localizer of a :class:`~sprint_map.map.SprintMap` is made of, the part
of its service API (:class:`~sprint_map.facade.service.MapService`) that makes localizers: a view
of the map per localizer, a component cache shared by threads, a new drive's centring and the
map's mean condition, and a drive's GNSS aid against the positions the map stores.

The pooled condition prior and the position index are cached here, one per map, until the
map changes.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from sprint_map.frontend.centring import CentringStats, DriveCentring
from sprint_map.storage.records import SequenceRecord
from sprint_map.storage.store import MapStore
from sprint_map.util.arrays import Float64Array

if TYPE_CHECKING:  # imported where used: reading a map needs no HMM
    from sprint_map.config import MapConfig
    from sprint_map.hmm.cache import ComponentCache
    from sprint_map.localize.gnss import GnssAid, PositionIndex
    from sprint_map.localize.localizer import MapView

__all__ = ["MapSupply", "SuppliedMap"]


class SuppliedMap(Protocol):
    """What :class:`MapSupply` reads of its map (:class:`sprint_map.map.SprintMap` is one)."""

    @property
    def config(self) -> MapConfig: ...

    @property
    def store(self) -> MapStore: ...

    def stats(self) -> dict[str, int]: ...

    def sequences(self) -> list[SequenceRecord]: ...

    def positions(self, seq_id: int) -> Float64Array | None: ...


class MapSupply:
    """What a localizer of ``smap`` is made of (see the module docstring).

    Parameters
    ----------
    smap : SuppliedMap
        The map (:class:`~sprint_map.map.SprintMap`).
    """

    def __init__(self, smap: SuppliedMap) -> None:
        self.map = smap
        self.store = smap.store
        #: positions read so far (seq_id -> (first vertex, rows)) and the index of a snapshot
        self._placed: dict[int, tuple[int, Float64Array]] = {}
        self._position_index: tuple[tuple[Any, ...], PositionIndex] | None = None
        #: the pooled condition prior and the map counts it was pooled at
        self._prior: tuple[tuple[int, int], CentringStats | None] | None = None

    def view(self) -> MapView:
        """A new view of the map for one :class:`~sprint_map.localize.localizer.Localizer`
        (what it reads: k-NN search, vertex locations, components and their edges, from
        pinned LMDB snapshots).

        Returns
        -------
        MapView
            The view (:class:`sprint_map.localize.stored_view.StoredMapView`).

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map({"monday": 30}, dim=16) as m:
        ...     print(m.service.view().vertices)
        30
        """
        from sprint_map.localize.stored_view import StoredMapView

        return StoredMapView(self.store)

    def shared_cache(self) -> ComponentCache:
        """A thread-safe component cache of the map's ``hmm.cache_budget_bytes``, for
        localizers that run in several threads over this map (``Localizer(..., cache=)``):
        each component is loaded once for all of them.

        Returns
        -------
        ComponentCache
            The cache (:class:`sprint_map.hmm.cache.SharedComponentCache`).
        """
        from sprint_map.hmm.cache import SharedComponentCache

        return SharedComponentCache(self.map.config.hmm.cache_budget_bytes)

    def drive_centring(self) -> DriveCentring:
        """A new drive's centring (:mod:`sprint_map.frontend.centring`, ``config.centring``):
        every drive's descriptors pass through one, in drive order, before they are searched
        or stored, so that the map answers by place, not by condition. Its prior is the map's
        mean condition now (:meth:`condition_prior`).

        Returns
        -------
        DriveCentring
            A fresh one (it has seen no frame).

        Examples
        --------
        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> road = np.random.default_rng(0).standard_normal((30, 16)).astype(np.float32)
        >>> with example_map(dim=16) as m:
        ...     rows = m.service.drive_centring().apply(road)  # centring "none": as given
        ...     print(rows.shape, bool((rows == road).all()), m.service.condition_prior())
        (30, 16) True None

        Notes
        -----
        O(dim), or O(sequences * dim) the first time after a commit (the prior is pooled
        again from the drives' statistics).
        """
        config = self.map.config
        return DriveCentring(config.centring, config.dim, self.condition_prior())

    def condition_prior(self) -> CentringStats | None:
        """The map's mean condition: the frame-weighted mean of its drives' statistics
        (:meth:`SprintMap.drive_stats <sprint_map.facade.reading.MapReading.drive_stats>`).
        Cached until the map changes; O(sequences * dim) when pooled.

        Returns
        -------
        CentringStats or None
            None for a map without any statistics, or whose centring uses no prior.
        """
        centring = self.map.config.centring
        if not centring.enabled or not centring.prior_frames:
            return None
        counts = self.store.stats()
        key = (counts["sequences"], counts["vertices"])
        if self._prior is None or self._prior[0] != key:
            pooled = CentringStats.pool(CentringStats(frames, mean)
                                        for _, frames, mean in self.store.all_drive_stats())
            self._prior = (key, pooled)
        return self._prior[1]

    def gnss_aid(self, fixes: np.ndarray | None, frames: int | None, *, index: bool = True
                 ) -> GnssAid | None:
        """A drive's GNSS ``fixes`` against the map's positions (:mod:`sprint_map.localize.gnss`).

        Parameters
        ----------
        fixes : numpy.ndarray, optional
            (N, 2 or 3): ``x, y[, sigma_m]`` per frame (NaN rows: none), in the frame of the
            map's positions.
        frames : int, optional
            The drive's length, if known (then the fixes must be one per frame).
        index : bool
            False: only check the fixes.

        Returns
        -------
        GnssAid or None
            None when there are no fixes, ``index`` is False, or the map stores no position
            (GNSS changes nothing then).

        Raises
        ------
        InputError
            Fixes not one per frame, out of range, or with a ``sigma_m`` <= 0
            (:func:`sprint_map.localize.gnss.validate_fixes`).
        """
        from sprint_map.localize.gnss import GnssAid, validate_fixes

        if fixes is None:
            return None
        gnss = self.map.config.gnss
        checked = validate_fixes(fixes, frames, gnss.sigma_m)
        if not index:
            return None
        positions = self.position_index()
        return GnssAid(gnss, positions, checked) if positions.size else None

    def position_index(self) -> PositionIndex:
        """The positions the map stores, by vertex and in a KD-tree, as of now; kept until the
        map changes.

        Returns
        -------
        PositionIndex
            The index (:class:`sprint_map.localize.gnss.PositionIndex`).

        Notes
        -----
        O(n log n) for the n placed vertices when the map changed (positions of sequences
        read before are kept: each sequence is read once); O(1) otherwise.
        """
        from sprint_map.localize.gnss import PositionIndex

        smap = self.map
        stats = smap.stats()
        key = (stats["vertices"], stats["sequences"], self.store.removed_vertices(),
               str(self.store.data_path))
        if self._position_index is not None and self._position_index[0] == key:
            return self._position_index[1]
        live = {seq.seq_id: seq for seq in smap.sequences()}
        placed = {i: p for i, p in self._placed.items()
                  if i in live and live[i].first_vertex == p[0]}
        for seq_id, seq in live.items():
            if seq_id not in placed:
                rows = smap.positions(seq_id)
                placed[seq_id] = (seq.first_vertex, rows if rows is not None
                                  else np.empty((0, 2)))
        self._placed = placed
        index = PositionIndex(stats["vertices"], [p for p in placed.values() if len(p[1])],
                              smap.config.gnss.map_sigma_m)
        self._position_index = (key, index)
        return index
