"""MapReading: what :class:`~sprint_map.map.SprintMap` reads of its map: sequences and their
vertices, descriptors, thumbnails, drive statistics, components, edges and exports; positions and
frames (:class:`~sprint_map.facade.positions.MapPositions`) and k-NN search
(:class:`~sprint_map.facade.search.MapSearch`) are its bases.

A mixin of the facade over its store (:class:`~sprint_map.storage.store.MapStore`); each call
reads one consistent snapshot and changes nothing. Every read of the map's LMDB may raise
:class:`~sprint_map.errors.MapCorruptError` (a record that does not decode, a damaged map) or
:class:`~sprint_map.errors.StorageIOError` (LMDB cannot be read); each method's ``Raises`` names
them once more beside the errors of its arguments. The examples build a small map of random
descriptors in a temporary directory.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from typing import TYPE_CHECKING

from sprint_map.facade.positions import MapPositions
from sprint_map.facade.search import MapSearch
from sprint_map.frontend.centring import CentringStats
from sprint_map.storage.provenance import edge_table
from sprint_map.storage.records import ComponentInfo, EdgeTable, SequenceRecord
from sprint_map.util.arrays import Descriptors

if TYPE_CHECKING:  # imported where used
    from sprint_map.export.report import ExportReport
    from sprint_map.storage.removal import RemovedRanges

__all__ = ["MapReading"]


class MapReading(MapPositions, MapSearch):
    """The facade's reads (see the module docstring) over ``store``."""


    def sequence(self, seq_id: int) -> SequenceRecord:
        """The record of sequence ``seq_id``. O(log n_sequences).

        Parameters
        ----------
        seq_id : int
            A sequence id (as :meth:`sequences` lists them; never reused).

        Returns
        -------
        SequenceRecord
            Its ``seq_id``, ``name``, ``length`` (frames), ``first_vertex``, ``created`` (unix
            time) and ``source``.

        Raises
        ------
        UnknownSequenceError
            No live sequence ``seq_id`` (never added, or removed).
        MapCorruptError, StorageIOError
            A damaged map; LMDB cannot be read.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> smap = example_map({"mon": 5})
        >>> record = smap.sequence(0)
        >>> record.name, record.length, record.first_vertex
        ('mon', 5, 0)
        >>> smap.sequence(7)
        Traceback (most recent call last):
            ...
        sprint_map.errors.UnknownSequenceError: no sequence 7 in the map
        >>> smap.close()
        """
        return self.store.sequence(seq_id)

    def sequences(self) -> list[SequenceRecord]:
        """Every live sequence's record, in id order (removed ones are gone). O(n_sequences).

        Returns
        -------
        list of SequenceRecord
            As :meth:`sequence` gives them.

        Raises
        ------
        MapCorruptError, StorageIOError
            A damaged map; LMDB cannot be read.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> smap = example_map({"mon": 5, "tue": 3})
        >>> [(s.seq_id, s.name, s.first_vertex) for s in smap.sequences()]
        [(0, 'mon', 0), (1, 'tue', 5)]
        >>> smap.close()
        """
        return self.store.sequences()

    def sequence_by_name(self, name: str) -> SequenceRecord:
        """The record of the sequence named ``name``. O(log n_sequences).

        Parameters
        ----------
        name : str
            A sequence name (unique in a map; ``seq-<id>`` when none was given).

        Returns
        -------
        SequenceRecord
            As :meth:`sequence` gives it.

        Raises
        ------
        UnknownSequenceError
            No sequence has that name (none can have ``""`` or a name with a newline).
        InputError
            ``name`` is not UTF-8 text.
        MapCorruptError, StorageIOError
            A damaged map; LMDB cannot be read.

        Examples
        --------
        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> smap = example_map({"mon": 5})
        >>> _ = smap.add_sequence(np.ones((3, 8), np.float32))  # named by its id
        >>> smap.sequence_by_name("seq-1").length
        3
        >>> smap.sequence_by_name("sun")
        Traceback (most recent call last):
            ...
        sprint_map.errors.UnknownSequenceError: no sequence named 'sun' in the map
        >>> smap.close()
        """
        return self.store.sequence_by_name(name)

    def locate(self, vertex_ids: Iterable[int]) -> list[tuple[int, int]]:
        """``(seq_id, image_id)`` of each vertex id (as :meth:`search` returns them).
        O(log n_sequences) per vertex.

        Parameters
        ----------
        vertex_ids : iterable of int
            Vertex ids (a sequence's frame ``i`` is vertex ``first_vertex + i``).

        Returns
        -------
        list of (int, int)
            One ``(seq_id, image_id)`` per vertex id, in order.

        Raises
        ------
        UnknownSequenceError
            A vertex of a removed sequence (its id stays until ``compact``).
        MapCorruptError
            A vertex id outside ``0..vertices-1`` (no search returns one); a damaged map.
        StorageIOError
            LMDB cannot be read.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> smap = example_map({"mon": 5, "tue": 3})
        >>> smap.locate([0, 4, 5, 7])
        [(0, 0), (0, 4), (1, 0), (1, 2)]
        >>> smap.close()
        """
        return self.store.locate(vertex_ids)

    def component_of(self, seq_id: int) -> int:
        """The component sequence ``seq_id`` lies in: its union-find root's sequence id (the
        drives joined to it by edges share it). O(alpha(n_sequences)) amortised.

        Parameters
        ----------
        seq_id : int
            A sequence id.

        Returns
        -------
        int
            The component's id, a sequence id of the component.

        Raises
        ------
        UnknownSequenceError
            No live sequence ``seq_id``.
        MapCorruptError, StorageIOError
            A damaged map; LMDB cannot be read.

        Examples
        --------
        A second drive of the same road merges into the first one's component:

        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> smap = example_map({"mon": 30, "far": 30})
        >>> road = smap.descriptors(0)
        >>> again = road + 0.01 * np.random.default_rng(1).standard_normal(road.shape)
        >>> smap.ingest(again, name="tue").added.edges_added > 0
        True
        >>> [smap.component_of(s) for s in (0, 1, 2)]
        [0, 1, 0]
        >>> smap.close()
        """
        return self.store.component_of(seq_id)

    def components(self) -> list[ComponentInfo]:
        """Every component with its sequences and vertex count. O(n_sequences).

        Returns
        -------
        list of ComponentInfo
            ``component`` (its id: :meth:`component_of`), ``sequences`` (ids) and ``vertices``.

        Raises
        ------
        MapCorruptError, StorageIOError
            A damaged map; LMDB cannot be read.

        Examples
        --------
        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> smap = example_map({"mon": 30, "far": 10})
        >>> road = smap.descriptors(0)
        >>> _ = smap.ingest(road + 0.01 * np.random.default_rng(1).standard_normal(road.shape))
        >>> smap.components()
        [ComponentInfo(component=0, sequences=[0, 2], vertices=60),
         ComponentInfo(component=1, sequences=[1], vertices=10)]
        >>> smap.close()
        """
        return self.store.components()

    def export_graphml(self, path: str | os.PathLike[str], level: str | None = None
                       ) -> ExportReport:
        """Write the map as GraphML for networkx, Gephi or Cytoscape.

        Edges carry their probability and provenance; the file is published whole or not at
        all. See :mod:`sprint_map.export.graphml`. O(V + E) time; the vertex level is streamed.

        Parameters
        ----------
        path : str or path-like
            The file to write (replaced if it exists), outside the map's directory.
        level : {"vertex", "sequence"}, optional
            A node per frame, or a node per drive; by default the vertex level up to
            ``VERTEX_LEVEL_LIMIT`` (100,000) vertices, the sequence level beyond.

        Returns
        -------
        ExportReport
            What was written: ``level``, ``sequences``, ``nodes``, ``edges``, ``bytes``.

        Raises
        ------
        InputError
            An unknown ``level``; ``path`` a directory, inside the map, or not writable.
        StorageIOError
            Writing the file failed (nothing is published); LMDB cannot be read.
        MapCorruptError
            A damaged map.

        Examples
        --------
        >>> import os, shutil, tempfile
        >>> from sprint_map.examples import example_map
        >>> smap = example_map({"mon": 5})
        >>> out = tempfile.mkdtemp()
        >>> report = smap.export_graphml(os.path.join(out, "map.graphml"))
        >>> report.level, report.nodes, report.edges
        ('vertex', 5, 0)
        >>> smap.export_graphml(os.path.join(out, "map.graphml"), level="drive")
        Traceback (most recent call last):
            ...
        sprint_map.errors.InputError: export level must be one of vertex, sequence, not 'drive'
        >>> smap.close(); shutil.rmtree(out)
        """
        from sprint_map.export import export_graphml

        return export_graphml(self.store, path, level)

    def export_csv(self, directory: str | os.PathLike[str]) -> ExportReport:
        """Write ``sequences.csv``, ``vertices.csv`` (with positions) and ``edges.csv`` into
        ``directory``, streamed, all three published together. See
        :mod:`sprint_map.export.tables`. O(V + E) time, O(S) memory.

        Parameters
        ----------
        directory : str or path-like
            Where to write them (made if absent; files of those names are replaced), outside
            the map's directory.

        Returns
        -------
        ExportReport
            ``files`` (the three paths), ``nodes`` (vertex rows), ``edges``, ``bytes``.

        Raises
        ------
        InputError
            ``directory`` is a file, inside the map, or cannot be made or written.
        StorageIOError
            Writing a file failed (none is published); LMDB cannot be read.
        MapCorruptError
            A damaged map.

        Examples
        --------
        >>> import os, shutil, tempfile
        >>> from sprint_map.examples import example_map
        >>> smap = example_map({"mon": 5})
        >>> out = tempfile.mkdtemp()
        >>> report = smap.export_csv(out)
        >>> [os.path.basename(f) for f in report.files], report.nodes
        (['sequences.csv', 'vertices.csv', 'edges.csv'], 5)
        >>> smap.close(); shutil.rmtree(out)
        """
        from sprint_map.export import export_csv

        return export_csv(self.store, directory)

    def export_geojson(self, path: str | os.PathLike[str]) -> ExportReport:
        """Write drives as lines on their positions and edges as segments, as GeoJSON
        (latitude/longitude when the map keeps a :meth:`geo_frame`, else its planar ``x, y``).
        See :mod:`sprint_map.export.geojson`. O(V + E).

        Parameters
        ----------
        path : str or path-like
            The file to write (replaced if it exists), outside the map's directory.

        Returns
        -------
        ExportReport
            ``nodes`` (drives drawn), ``edges`` (segments drawn), ``skipped_edges`` (edges
            with an end without a position), ``bytes``.

        Raises
        ------
        InputError
            No drive has positions (nothing is written); ``path`` a directory, inside the
            map, or not writable.
        StorageIOError
            Writing the file failed (nothing is published); LMDB cannot be read.
        MapCorruptError
            A damaged map.

        Examples
        --------
        >>> import os, shutil, tempfile
        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> rng = np.random.default_rng(0)
        >>> smap = example_map()
        >>> rows = rng.standard_normal((5, 8)).astype(np.float32)
        >>> _ = smap.add_sequence(rows, name="mon", positions=np.c_[np.arange(5.0), np.zeros(5)])
        >>> out = tempfile.mkdtemp()
        >>> smap.export_geojson(os.path.join(out, "map.geojson")).nodes
        1
        >>> smap.close(); shutil.rmtree(out)
        """
        from sprint_map.export import export_geojson

        return export_geojson(self.store, path)

    def thumbnail(self, seq_id: int, image_id: int) -> bytes | None:
        """The JPEG thumbnail of frame ``image_id`` of sequence ``seq_id``. O(log n).

        Parameters
        ----------
        seq_id, image_id : int
            The frame: a sequence id and a frame number of it (``0..length-1``).

        Returns
        -------
        bytes or None
            The JPEG, or None when the drive was ingested without ``--thumbnails``.

        Raises
        ------
        UnknownSequenceError
            No such sequence, or no such frame in it.
        MapCorruptError, StorageIOError
            A damaged map; LMDB cannot be read.

        Examples
        --------
        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> rng = np.random.default_rng(0)
        >>> smap = example_map()
        >>> jpegs = [b"\\xff\\xd8 frame %d \\xff\\xd9" % i for i in range(3)]  # SOI ... EOI
        >>> rows = rng.standard_normal((3, 8)).astype(np.float32)
        >>> _ = smap.add_sequence(rows, name="mon", thumbnails=jpegs)
        >>> smap.thumbnail(0, 2)
        b'\\xff\\xd8 frame 2 \\xff\\xd9'
        >>> smap.thumbnail(0, 3)
        Traceback (most recent call last):
            ...
        sprint_map.errors.UnknownSequenceError: sequence 0 has no image 3 (it has 3)
        >>> smap.close()
        """
        return self.store.thumbnail(seq_id, image_id)

    def drive_stats(self, seq: int | str) -> CentringStats | None:
        """The statistics sequence ``seq`` was stored with: its drive's frames and mean
        descriptor as described, the drive's condition (:mod:`sprint_map.frontend.centring`).
        O(dim).

        Parameters
        ----------
        seq : int or str
            A sequence id or name.

        Returns
        -------
        CentringStats or None
            ``frames`` and ``mean`` (float32, ``dim``); None for a sequence stored before
            drive statistics existed.

        Raises
        ------
        UnknownSequenceError
            No such sequence.
        InputError
            A name that is not UTF-8 text.
        MapCorruptError, StorageIOError
            A damaged map; LMDB cannot be read.

        Examples
        --------
        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> smap = example_map(dim=4)
        >>> _ = smap.add_sequence(np.array([[1, 0, 0, 0], [0, 1, 0, 0]], np.float32), name="mon")
        >>> stats = smap.drive_stats("mon")
        >>> stats.frames, stats.mean.tolist()
        (2, [0.5, 0.5, 0.0, 0.0])
        >>> smap.close()
        """
        seq_id = seq if isinstance(seq, int) else self.sequence_by_name(seq).seq_id
        got = self.store.drive_stats(seq_id)
        return None if got is None else CentringStats(*got)

    def thumbnail_count(self, seq_id: int) -> int:
        """How many thumbnails sequence ``seq_id`` keeps (a drive keeps one per frame or
        none). O(log n + count).

        Parameters
        ----------
        seq_id : int
            A sequence id.

        Returns
        -------
        int
            Its length, or 0.

        Raises
        ------
        UnknownSequenceError
            No such sequence.
        MapCorruptError, StorageIOError
            A damaged map; LMDB cannot be read.

        Examples
        --------
        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> smap = example_map()
        >>> rows = np.ones((3, 8), np.float32)
        >>> _ = smap.add_sequence(rows, thumbnails=[b"\\xff\\xd8 jpeg \\xff\\xd9"] * 3)
        >>> _ = smap.add_sequence(rows)
        >>> smap.thumbnail_count(0), smap.thumbnail_count(1)
        (3, 0)
        >>> smap.close()
        """
        return self.store.thumbnail_count(seq_id)

    def edge_table(self) -> EdgeTable:
        """Every edge as arrays of vertex ids, probabilities and provenance, in ``(src, dst)``
        order (for summaries of large maps; ``SprintMap.edges`` gives ``(seq, image)``
        records). O(E), one snapshot; see :func:`sprint_map.storage.provenance.edge_table`.

        Returns
        -------
        EdgeTable
            ``src``, ``dst`` (vertex ids, int64), ``prob`` (float64) and ``added_by`` (the
            sequence whose merge wrote the edge; -1 for none), one entry per directed edge.

        Raises
        ------
        MapCorruptError, StorageIOError
            A damaged map (an edge record of the wrong size); LMDB cannot be read.

        Examples
        --------
        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> smap = example_map({"mon": 30})
        >>> road = smap.descriptors(0)
        >>> _ = smap.ingest(road + 0.01 * np.random.default_rng(1).standard_normal(road.shape))
        >>> table = smap.edge_table()
        >>> len(table) == smap.stats()["edges"], set(table.added_by.tolist())
        (True, {1})
        >>> int(table.src[0]), int(table.dst[0])  # mon's frame 0 -> the new drive's frame 0
        (0, 30)
        >>> smap.close()
        """
        return edge_table(self.store)

    def descriptors(self, seq_id: int) -> Descriptors:
        """The descriptor rows of sequence ``seq_id`` as stored (centred, if the map's
        ``centring`` is on; as given otherwise). O(length * dim) bytes read.

        Parameters
        ----------
        seq_id : int
            A sequence id.

        Returns
        -------
        ndarray of float32, shape (length, dim)
            A read-only memory-mapped view when the rows lie in one shard file (valid while
            the map is open), else a copy.

        Raises
        ------
        UnknownSequenceError
            No live sequence ``seq_id``.
        MapCorruptError, StorageIOError
            A damaged map (a shard shorter than its rows); a shard or LMDB cannot be read.

        Examples
        --------
        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> smap = example_map({"mon": 5})
        >>> rows = np.random.default_rng(0).standard_normal((5, 8)).astype(np.float32)
        >>> got = smap.descriptors(0)
        >>> got.shape, got.dtype, bool((got == rows).all())
        ((5, 8), dtype('float32'), True)
        >>> del got; smap.close()
        """
        return self.store.descriptors(seq_id)

    def vertex_rows(self, start: int, stop: int | None = None) -> Descriptors:
        """Descriptor rows of vertex ids ``start..stop-1`` as stored, removed sequences' rows
        included (their ids stay until ``compact``): what a retrieval shard of the fleet loads
        (:mod:`sprint_map.fleet.shards`). O((stop - start) * dim) bytes read.

        Parameters
        ----------
        start : int
            The first vertex id.
        stop : int, optional
            One past the last; None: up to the last committed vertex.

        Returns
        -------
        ndarray of float32, shape (stop - start, dim)
            A read-only memory-mapped view when the range lies in one shard file, else a copy.

        Raises
        ------
        IndexError
            A range outside ``0..vertices`` (or ``stop < start``).
        MapCorruptError, StorageIOError
            A damaged map; a shard or LMDB cannot be read.

        Examples
        --------
        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> smap = example_map(dim=2)
        >>> _ = smap.add_sequence(np.array([[0, 1], [2, 3], [4, 5]], np.float32), name="mon")
        >>> _ = smap.add_sequence(np.array([[6, 7]], np.float32), name="tue")
        >>> _ = smap.remove_sequences(["mon"])
        >>> smap.vertex_rows(1).tolist()  # mon's rows stay until compact
        [[2.0, 3.0], [4.0, 5.0], [6.0, 7.0]]
        >>> smap.close()
        """
        total = self.stats()["vertices"]
        return self.store.shards.rows(start, total if stop is None else stop, total)

    def removed_ranges(self) -> RemovedRanges:
        """The vertex ranges of removed sequences, hidden from every search until ``compact``
        reclaims them. O(removed) (cached until the next removal).

        Returns
        -------
        RemovedRanges
            ``first``, ``last`` (inclusive) and ``seq_ids`` arrays, sorted; ``count``
            (ranges), ``vertices`` and ``contains(vertex_ids)`` (a mask).

        Raises
        ------
        MapCorruptError, StorageIOError
            A damaged map; LMDB cannot be read.

        Examples
        --------
        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> smap = example_map({"mon": 5, "tue": 3})
        >>> _ = smap.remove_sequences(["mon"])
        >>> removed = smap.removed_ranges()
        >>> removed.count, removed.vertices, removed.contains(np.array([4, 5])).tolist()
        (1, 5, [True, False])
        >>> smap.close()
        """
        with self.store.env.read() as txn:
            return self.store.removed_ranges(txn)

    def stats(self) -> dict[str, int]:
        """Counts of the map, from its meta record. O(1).

        Returns
        -------
        dict of str to int
            ``sequences`` and ``components`` (live), ``vertices`` (every vertex id given, a
            removed sequence's included until ``compact``) and ``edges`` (directed).

        Raises
        ------
        MapCorruptError, StorageIOError
            A counter missing or of the wrong size (a damaged map); LMDB cannot be read.

        Examples
        --------
        >>> from sprint_map.examples import example_map
        >>> smap = example_map({"mon": 5})
        >>> smap.stats()
        {'sequences': 1, 'vertices': 5, 'edges': 0, 'components': 1}
        >>> smap.close()
        """
        return self.store.stats()

