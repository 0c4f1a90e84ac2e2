"""MapReading: what :class:`~sprint_map.map.SprintMap` reads of its map: sequences and their
vertices, descriptors, positions and thumbnails, components, exports, and k-NN search.

A mixin of the facade over its store (:class:`~sprint_map.storage.store.MapStore`); each call
reads one consistent snapshot. Nothing here changes the map but the geographic frame that
:meth:`MapReading.metric_positions` sets once, the first time a map is given latitudes (after
checking that the map keeps no planar positions: a map keeps one frame).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from typing import TYPE_CHECKING

from sprint_map.errors import InputError
from sprint_map.frontend.centring import CentringStats
from sprint_map.storage.index.model import cap_threads
from sprint_map.storage.provenance import edge_table
from sprint_map.storage.records import ComponentInfo, EdgeTable, SequenceRecord
from sprint_map.storage.store import MapStore
from sprint_map.util.arrays import Descriptors, DescriptorsLike, Float64Array, SearchResult
from sprint_map.util.geo import GeoFrame

if TYPE_CHECKING:  # imported where used
    from sprint_map.export.report import ExportReport
    from sprint_map.frontend.positions import Positions
    from sprint_map.storage.removal import RemovedRanges

__all__ = ["MapReading"]


class MapReading:
    """The facade's reads (see the module docstring) over ``store``."""

    store: MapStore

    def sequence(self, seq_id: int) -> SequenceRecord:
        return self.store.sequence(seq_id)

    def sequences(self) -> list[SequenceRecord]:
        return self.store.sequences()

    def sequence_by_name(self, name: str) -> SequenceRecord:
        """The sequence named ``name`` (UnknownSequenceError if none). O(log n_sequences)."""
        return self.store.sequence_by_name(name)

    def locate(self, vertex_ids: Iterable[int]) -> list[tuple[int, int]]:
        """``(seq_id, image_id)`` of each vertex id (as :meth:`search` returns them).
        O(log n_sequences) per vertex."""
        return self.store.locate(vertex_ids)

    def component_of(self, seq_id: int) -> int:
        return self.store.component_of(seq_id)

    def components(self) -> list[ComponentInfo]:
        return self.store.components()

    def export_graphml(self, path: str | os.PathLike[str], level: str | None = None
                       ) -> ExportReport:
        """Write the map as GraphML for networkx, Gephi or Cytoscape.

        ``level`` ``"vertex"`` (a node per frame, streamed) or ``"sequence"`` (a node per
        drive); by default the vertex level up to ``VERTEX_LEVEL_LIMIT`` (100,000) vertices,
        the sequence level beyond. Edges carry their probability and provenance. See
        :mod:`sprint_map.export.graphml`.
        """
        from sprint_map.export import export_graphml

        return export_graphml(self.store, path, level)

    def export_csv(self, directory: str | os.PathLike[str]) -> ExportReport:
        """Write ``sequences.csv``, ``vertices.csv`` (with positions) and ``edges.csv`` into
        ``directory``, streamed. See :mod:`sprint_map.export.tables`."""
        from sprint_map.export import export_csv

        return export_csv(self.store, directory)

    def export_geojson(self, path: str | os.PathLike[str]) -> ExportReport:
        """Write drives as lines on their positions and edges as segments, as GeoJSON.

        Raises
        ------
        InputError
            No drive has positions. See :mod:`sprint_map.export.geojson`.
        """
        from sprint_map.export import export_geojson

        return export_geojson(self.store, path)

    def thumbnail(self, seq_id: int, image_id: int) -> bytes | None:
        """The JPEG thumbnail of frame ``image_id`` of sequence ``seq_id``, or None when the
        drive was ingested without ``--thumbnails``. O(log n).

        Raises
        ------
        UnknownSequenceError
            No such sequence, or no such frame in it.
        """
        return self.store.thumbnail(seq_id, image_id)

    def drive_stats(self, seq: int | str) -> CentringStats | None:
        """The statistics sequence ``seq`` (id or name) was stored with: its drive's frames and
        mean descriptor as described, the drive's condition (:mod:`sprint_map.frontend.centring`),
        or None for a sequence stored before drive statistics existed. O(dim).

        Raises
        ------
        UnknownSequenceError
            No such sequence.
        """
        seq_id = seq if isinstance(seq, int) else self.sequence_by_name(seq).seq_id
        got = self.store.drive_stats(seq_id)
        return None if got is None else CentringStats(*got)

    def thumbnail_count(self, seq_id: int) -> int:
        """How many thumbnails sequence ``seq_id`` keeps: its length, or 0. O(log n + count).

        Raises
        ------
        UnknownSequenceError
            No such sequence.
        """
        return self.store.thumbnail_count(seq_id)

    def edge_table(self) -> EdgeTable:
        """Every edge as arrays of vertex ids, probabilities and provenance (for summaries of
        large maps; :meth:`edges` gives ``(seq, image)`` records). O(E), one snapshot; see
        :func:`sprint_map.storage.provenance.edge_table`."""
        return edge_table(self.store)

    def descriptors(self, seq_id: int) -> Descriptors:
        return self.store.descriptors(seq_id)

    def positions(self, seq_id: int) -> Float64Array | None:
        """``(length, 4)`` ``x, y, heading_deg, timestamp`` of a sequence (a fifth column
        ``sigma_m`` when a fix has an accuracy; NaN rows: frames without a fix), or None.
        O(length)."""
        return self.store.positions(seq_id)

    def geo_frame(self) -> GeoFrame | None:
        """The UTM zone this map keeps latitude/longitude in (set by the first geographic
        positions it was given), or None. O(1)."""
        record = self.store.geo_frame()
        return None if record is None else GeoFrame.from_dict(record)

    def position_frame(self) -> GeoFrame | str | None:
        """The frame of the positions this map keeps: its :class:`GeoFrame` (UTM zone) when
        it was given latitude/longitude, ``"planar"`` when it holds positions given as
        ``x, y`` (no geographic frame recorded), None before any position. O(1)."""
        frame = self.geo_frame()
        if frame is not None:
            return frame
        return "planar" if self.store.has_positions() else None

    def metric_positions(self, positions: Positions | None) -> Float64Array | None:
        """Positions as the map stores them (``(n, 5)`` ``x, y, heading, time, sigma_m``):
        latitude/longitude are projected into the map's UTM zone, which the first geographic
        positions a map is given choose (the zone of their first fix) and store, once, in a
        transaction of their own (a read-only map only projects into it). Planar positions
        are taken as they are. O(n).

        Raises
        ------
        InputError
            Geographic positions without a single fix; positions of the other frame than the
            map's (:meth:`check_position_frames`).
        """
        return self.metric_positions_of([positions])[0]

    def check_position_frames(self, tables: Sequence[Positions | None]) -> None:
        """Refuse, before anything changes, positions that do not share one frame with each
        other and with the map (:meth:`position_frame`): latitude/longitude into a map of
        planar ``x, y`` or the reverse, or both kinds in one call. O(len(tables)).

        Raises
        ------
        InputError
            Naming the frame the map keeps and the one given.
        """
        kinds = {"geographic" if t.geographic else "planar" for t in tables if t is not None}
        if len(kinds) > 1:
            raise InputError("positions mix latitude/longitude and planar x, y: a map keeps one "
                             "frame (give all drives lat,lon or all x,y)")
        if not kinds:
            return
        given = kinds.pop()
        kept = self.position_frame()
        if kept is None or (given == "planar") == (kept == "planar"):
            return
        if given == "planar":
            assert isinstance(kept, GeoFrame)
            raise InputError(f"planar x, y positions given to a map of latitude/longitude (kept "
                             f"in UTM zone {kept.zone}{'S' if kept.south else 'N'}): give "
                             "lat,lon positions, or use another map")
        raise InputError("latitude/longitude positions given to a map of planar x, y "
                         "positions: give x,y positions in the map's frame, or use another map")

    def metric_positions_of(self, tables: Sequence[Positions | None]
                            ) -> list[Float64Array | None]:
        """:meth:`metric_positions` of several drives' positions (one ingest), checked
        together first (:meth:`check_position_frames`): nothing is stored when any is refused.
        O(total rows)."""
        self.check_position_frames(tables)
        out: list[Float64Array | None] = []
        for positions in tables:
            if positions is None or not positions.geographic:
                out.append(None if positions is None else positions.rows())
                continue
            frame = self.geo_frame()
            if frame is None:
                first = next((t.first_fix() for t in tables
                              if t is not None and t.first_fix() is not None), None)
                if first is None:
                    raise InputError("geographic positions without any fix: nothing to place")
                frame = GeoFrame.for_fix(*first)
                if not self.store.readonly:
                    frame = GeoFrame.from_dict(self.store.set_geo_frame(frame.to_dict()))
            out.append(positions.metric(frame).rows())
        return out

    def vertex_rows(self, start: int, stop: int | None = None) -> Descriptors:
        """Descriptor rows of vertex ids ``start..stop-1`` as stored (``stop`` None: up to the
        last committed vertex), removed sequences' rows included (their ids stay until
        ``compact``). A read-only view when the range lies in one shard file.

        Notes
        -----
        O((stop - start) * dim) bytes read; what a retrieval shard of the fleet loads
        (:mod:`sprint_map.fleet.shards`).
        """
        total = self.stats()["vertices"]
        return self.store.shards.rows(start, total if stop is None else stop, total)

    def removed_ranges(self) -> RemovedRanges:
        """The vertex ranges of removed sequences (hidden from every search). O(removed)."""
        with self.store.env.read() as txn:
            return self.store.removed_ranges(txn)

    def stats(self) -> dict[str, int]:
        """Counts of sequences, vertices, edges and components. O(1)."""
        return self.store.stats()

    def search(self, queries: DescriptorsLike, k: int) -> SearchResult:
        """Exact k-NN over all committed descriptors: ``(squared L2 distances, vertex ids)``.
        ``queries`` are in the map's space: a drive's descriptors pass through
        :meth:`~sprint_map.map.SprintMap.drive_centring` first."""
        return self.store.search(queries, k)

    def search_within(self, queries: DescriptorsLike, k: int, start: int,
                      stop: int | None = None) -> SearchResult:
        """:meth:`search` among vertex ids ``[start, stop)`` only, on the map's approximate
        index (ValueError while it is exact): what a retrieval shard of the fleet answers.
        O(the index segments holding ids of the range)."""
        return self.store.search_within(queries, k, start, stop)

    def index_segments(self) -> list[tuple[int, int]]:
        """Vertex ranges ``(start, stop)`` of the approximate index's sealed segments (none
        while it is exact): where retrieval shards cut the map. O(segments)."""
        return self.store.index_segments()

    @staticmethod
    def cap_search_threads(n: int) -> None:
        """Use at most ``n`` OpenMP threads for the searches of the calling thread from now on
        (any map; e.g. the service's batch searcher, whose other core answers HTTP)."""
        cap_threads(n)
