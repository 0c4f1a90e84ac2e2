"""SprintMap: the library's front door, composing the store, retrieval and the HMM.

The CLI is a thin layer over this class; everything it does can be done from Python::

    from sprint_map import MapConfig, SprintMap

    with SprintMap.create("city.map", MapConfig(dim=256)) as m:
        m.add_sequence(descriptors, name="monday")
    with SprintMap.open("city.map", readonly=True) as m:
        print(m.info())

The user's verbs are here and in the facade's mixins: its reads
(:class:`~sprint_map.facade.reading.MapReading`), localisation
(:class:`~sprint_map.facade.localizing.MapLocalizing`), drives added
(:class:`~sprint_map.facade.writing.MapWriting`), drives forgotten and the map's upkeep
(:class:`~sprint_map.facade.upkeep.MapUpkeep`). The plumbing that the service and the fleet need
(drives committed as they stream, prepared drives, views, caches) is the map's service API,
:attr:`SprintMap.service` (:class:`~sprint_map.facade.service.MapService`).
"""

from __future__ import annotations

import os
from typing import Any

from sprint_map.config import MapConfig
from sprint_map.facade.core import stored_config
from sprint_map.facade.writing import MapWriting
from sprint_map.storage.generation import current_data
from sprint_map.storage.provenance import list_edges
from sprint_map.storage.records import CheckReport, EdgeInfo, RepairReport
from sprint_map.storage.store import MapStore

__all__ = ["SprintMap", "stored_config"]


class SprintMap(MapWriting):
    """A persistent place-recognition map.

    Open with :meth:`create` or :meth:`open`, preferably as a context manager; one process at a
    time may open a map for writing, any number for reading (each sees consistent snapshots).
    Its reads (sequences, vertices, descriptors, positions, thumbnails, exports, search) are
    :class:`~sprint_map.facade.reading.MapReading`'s, its localisation
    :class:`~sprint_map.facade.localizing.MapLocalizing`'s, its changes (ingest, join)
    :class:`~sprint_map.facade.writing.MapWriting`'s and its upkeep (remove, unmerge, compact, ...)
    :class:`~sprint_map.facade.upkeep.MapUpkeep`'s; :attr:`service` is the API of the service
    and the fleet.

    Parameters
    ----------
    store : MapStore
        The open store (:meth:`create` and :meth:`open` make it).
    """

    # --- lifecycle --------------------------------------------------------------------------
    @classmethod
    def create(cls, path: str | os.PathLike[str], config: MapConfig) -> SprintMap:
        """Create an empty map in ``path`` and open it for writing.

        Parameters
        ----------
        path : str or path
            A directory that is absent or empty.
        config : MapConfig
            The map's configuration (its dimension, descriptor, HMM, merge rule, ...).

        Returns
        -------
        SprintMap
            The new map, open for writing.

        Raises
        ------
        MapExistsError
            ``path`` holds something already.
        InputError
            ``path`` is not UTF-8 text (nothing is created).

        Examples
        --------
        >>> import tempfile
        >>> from sprint_map import MapConfig, SprintMap
        >>> with SprintMap.create(tempfile.mkdtemp() + "/city.map", MapConfig(dim=16)) as m:
        ...     print(m.stats(), m.readonly)
        {'sequences': 0, 'vertices': 0, 'edges': 0, 'components': 0} False
        """
        return cls(MapStore.create(path, config))

    @classmethod
    def open(cls, path: str | os.PathLike[str], *, readonly: bool = False) -> SprintMap:
        """Open an existing map; a writer recovers interrupted writes first.

        Parameters
        ----------
        path : str or path
            The map's directory.
        readonly : bool
            Open for reading only (any number of readers may share a map).

        Returns
        -------
        SprintMap
            The map.

        Raises
        ------
        NotAMapError
            ``path`` holds no map.
        MapLockedError
            Another process is writing (raised at once, for a writer).
        SchemaVersionError
            The map was written by an unknown schema version.
        MapCorruptError
            The map violates an invariant that opening cannot repair.

        Notes
        -----
        O(1) in the size of the map: reads the meta record, and for a writer truncates the one
        shard that may hold uncommitted rows.

        Examples
        --------
        >>> import tempfile
        >>> from sprint_map import MapConfig, SprintMap
        >>> path = tempfile.mkdtemp() + "/city.map"
        >>> SprintMap.create(path, MapConfig(dim=16)).close()
        >>> with SprintMap.open(path, readonly=True) as m:
        ...     print(m.config.dim, m.readonly)
        16 True
        """
        return cls(MapStore.open(path, readonly=readonly, check_config=stored_config))

    def close(self) -> None:
        """Persist the index (writer) and release the map; closing twice does nothing. An
        index that could not be saved is a warning (:attr:`warnings`: it is a cache).

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> m = example_map(dim=16)
        >>> m.close()
        >>> m.closed
        True
        """
        self.store.close()

    def flush(self) -> None:
        """Persist the index now (it is a cache; LMDB is already durable).

        Raises
        ------
        StorageIOError
            The index could not be written.
        """
        self.store.flush()

    def __enter__(self) -> SprintMap:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def is_current(self) -> bool:
        """Whether the generation this map opened is still the live one: False once a
        ``compact`` selected a new copy (a reader then sees no later commit: reopen the map).
        O(1): reads the small ``CURRENT`` file.

        Returns
        -------
        bool
            True while no other generation was selected.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map(dim=16) as m:
        ...     print(m.is_current())
        True
        """
        return current_data(self.path) == self.store.data_path

    # --- reading and checking ---------------------------------------------------------------
    def edges(self, seq: int | str | None = None, *, added_by: int | str | None = None
              ) -> list[EdgeInfo]:
        """Edges between ``(seq, image)`` endpoints with their provenance (``added_by``: the
        drive whose merge created the edge; ``frame``; ``prob``), in vertex order
        (:func:`sprint_map.storage.provenance.list_edges` for the costs).

        Parameters
        ----------
        seq : int or str, optional
            Keep the edges touching that sequence (either end), by id or name.
        added_by : int or str, optional
            Keep those that drive added, i.e. what :meth:`unmerge` of it revokes.

        Returns
        -------
        list of EdgeInfo
            The edges, in vertex order.

        Raises
        ------
        UnknownSequenceError
            No sequence with that id or name.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map({"monday": 40}, dim=16) as m:
        ...     road = m.descriptors(0)
        ...     merged = m.ingest(road, name="tuesday").merged.sum()  # an edge each way
        ...     print(merged, len(m.edges(added_by="tuesday")), len(m.edges("monday")))
        40 80 80
        """
        return list_edges(self.store, None if seq is None else self.sequence_id(seq),
                          None if added_by is None else self.sequence_id(added_by))

    @staticmethod
    def repair(path: str | os.PathLike[str], *, seed: int = 0) -> RepairReport:
        """Repair the map at ``path`` as far as its own data allows, then check it (``sprint-map
        check --repair``; takes the writer lock; :func:`sprint_map.storage.repair.repair_map`).

        Parameters
        ----------
        path : str or path
            The map's directory (not open for writing elsewhere).
        seed : int
            Seeds the index's retraining, if it must be rebuilt.

        Returns
        -------
        RepairReport
            What was repaired, and the check after.

        Raises
        ------
        NotAMapError
            ``path`` holds no map.
        MapLockedError
            Another process is writing.

        Examples
        --------
        >>> import tempfile
        >>> from sprint_map import MapConfig, SprintMap
        >>> path = tempfile.mkdtemp() + "/city.map"
        >>> SprintMap.create(path, MapConfig(dim=16)).close()
        >>> SprintMap.repair(path).ok
        True
        """
        from sprint_map.frontend.thumbnails import decodes
        from sprint_map.storage.repair import repair_map

        return repair_map(path, seed=seed, check_config=stored_config, thumbnail_decodes=decodes)

    def check(self) -> CheckReport:
        """Verify every on-disk invariant (best on a map opened read-only); every thumbnail
        is decoded (:func:`sprint_map.frontend.thumbnails.decodes`).

        Returns
        -------
        CheckReport
            ``ok``, and the problems found.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map({"monday": 20}, dim=16) as m:
        ...     print(m.check().ok)
        True
        """
        from sprint_map.frontend.thumbnails import decodes
        from sprint_map.storage.check import check_map

        return check_map(self.store, thumbnail_decodes=decodes)

    def info(self) -> dict[str, Any]:
        """Summary for ``sprint-map info --json``. O(1) but for the directory walk.

        Returns
        -------
        dict
            Schema version, path, counts, dimension, descriptor, admission, index, projection,
            bytes on disk, removed vertices, generation and config.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> with example_map(dim=16) as m:
        ...     info = m.info()
        >>> info["dim"], info["sequences"], info["removed_vertices"]
        (16, 0, 0)
        """
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
