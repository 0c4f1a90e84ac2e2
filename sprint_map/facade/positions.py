"""MapPositions: where the facade's map keeps its frames: the positions of each sequence in the
map's one frame (latitude/longitude projected into a UTM zone, or planar x, y), and the checks that
keep a map to one frame.

A mixin of :class:`~sprint_map.facade.reading.MapReading` over the map's store. Nothing here changes
the map but the geographic frame that :meth:`MapPositions.metric_positions_of` sets once, the first
time a writable map is given latitudes (after checking that it keeps no planar positions). Every read
of the map's LMDB may raise :class:`~sprint_map.errors.MapCorruptError` or
:class:`~sprint_map.errors.StorageIOError`. The examples build a small map in a temporary directory.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from sprint_map.errors import InputError
from sprint_map.facade.core import MapCore
from sprint_map.util.arrays import Float64Array
from sprint_map.util.geo import GeoFrame

if TYPE_CHECKING:  # imported where used
    from sprint_map.frontend.positions import Positions

__all__ = ["MapPositions"]


class MapPositions(MapCore):
    """The facade's positions and frames (see the module docstring) over ``store``."""

    def positions(self, seq_id: int) -> Float64Array | None:
        """The positions sequence ``seq_id`` was stored with, in the map's frame
        (:meth:`position_frame`). O(length).

        Parameters
        ----------
        seq_id : int
            A sequence id.

        Returns
        -------
        ndarray of float64, shape (length, 4) or (length, 5), or None
            ``x, y, heading_deg, timestamp`` per frame, a fifth column ``sigma_m`` when a
            fix has an accuracy; NaN rows: frames without a fix; NaN columns: not given.
            None when the drive has no position.

        Raises
        ------
        UnknownSequenceError
            No live sequence ``seq_id``.
        MapCorruptError, StorageIOError
            A damaged map; LMDB cannot be read.

        Examples
        --------
        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> smap = example_map()
        >>> xy = np.array([[0.0, 0.0], [1.5, 0.0], [np.nan, np.nan]])  # frame 2: no fix
        >>> _ = smap.add_sequence(np.ones((3, 8), np.float32), name="mon", positions=xy)
        >>> smap.positions(0)
        array([[0. , 0. , nan, nan],
               [1.5, 0. , nan, nan],
               [nan, nan, nan, nan]])
        >>> _ = smap.add_sequence(np.ones((2, 8), np.float32), name="tue")
        >>> smap.positions(1) is None
        True
        >>> smap.close()
        """
        return self.store.positions(seq_id)

    def geo_frame(self) -> GeoFrame | None:
        """The UTM zone this map keeps latitude/longitude in (set by the first geographic
        positions it was given: :meth:`metric_positions`). O(1).

        Returns
        -------
        GeoFrame or None
            The zone and hemisphere; None for a map never given latitude/longitude.

        Raises
        ------
        MapCorruptError
            The stored frame record is not a JSON object (a damaged map).
        InputError
            A JSON record that is not a UTM frame (a damaged map).
        StorageIOError
            LMDB cannot be read.

        Examples
        --------
        See :meth:`metric_positions`.
        """
        record = self.store.geo_frame()
        return None if record is None else GeoFrame.from_dict(record)

    def position_frame(self) -> GeoFrame | str | None:
        """The frame of the positions this map keeps. O(1).

        Returns
        -------
        GeoFrame, "planar" or None
            Its :class:`GeoFrame` (UTM zone) when it was given latitude/longitude,
            ``"planar"`` when it holds positions given as ``x, y`` (no geographic frame
            recorded), None before any position.

        Raises
        ------
        MapCorruptError, StorageIOError
            A damaged map; LMDB cannot be read.

        Examples
        --------
        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> smap = example_map()
        >>> print(smap.position_frame())
        None
        >>> _ = smap.add_sequence(np.ones((2, 8), np.float32), positions=np.zeros((2, 2)))
        >>> smap.position_frame()
        'planar'
        >>> smap.close()
        """
        frame = self.geo_frame()
        if frame is not None:
            return frame
        return "planar" if self.store.has_positions() else None

    def metric_positions(self, positions: Positions | None) -> Float64Array | None:
        """Positions as the map stores them: latitude/longitude are projected into the map's
        UTM zone, which the first geographic positions a map is given choose (the zone of
        their first fix) and store, once, in a transaction of their own (a read-only map only
        projects into it). Planar positions are taken as they are. O(n).

        Parameters
        ----------
        positions : Positions or None
            A drive's positions (:mod:`sprint_map.frontend.positions`), planar or geographic.

        Returns
        -------
        ndarray of float64, shape (n, 5), or None
            ``x, y, heading_deg, time, sigma_m`` (NaN: not given; NaN ``x, y``: no fix);
            None for None.

        Raises
        ------
        InputError
            Geographic positions without a single fix; positions of the other frame than the
            map's (:meth:`check_position_frames`).
        StorageIOError
            Storing the frame failed (nothing is stored); LMDB cannot be read.
        MapCorruptError
            A damaged map.

        Examples
        --------
        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> from sprint_map.frontend.positions import Positions
        >>> smap = example_map()
        >>> latlon = np.array([[59.3293, 18.0686], [59.3294, 18.0688]])  # Stockholm
        >>> rows = smap.metric_positions(Positions(np.arange(2), latlon, geographic=True))
        >>> smap.geo_frame(), rows.shape
        (GeoFrame(zone=34, south=False), (2, 5))
        >>> np.round(rows[:, :2]).tolist()  # easting, northing (metres)
        [[333230.0, 6580391.0], [333242.0, 6580402.0]]
        >>> smap.close()
        """
        return self.metric_positions_of([positions])[0]

    def check_position_frames(self, tables: Sequence[Positions | None]) -> None:
        """Refuse, before anything changes, positions that do not share one frame with each
        other and with the map (:meth:`position_frame`): latitude/longitude into a map of
        planar ``x, y`` or the reverse, or both kinds in one call. O(len(tables)).

        Parameters
        ----------
        tables : sequence of Positions or None
            The positions of the drives of one call (None: a drive without).

        Returns
        -------
        None
            When they fit.

        Raises
        ------
        InputError
            Naming the frame the map keeps and the one given.
        MapCorruptError, StorageIOError
            A damaged map; LMDB cannot be read.

        Examples
        --------
        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> from sprint_map.frontend.positions import Positions
        >>> smap = example_map()
        >>> _ = smap.add_sequence(np.ones((2, 8), np.float32), positions=np.zeros((2, 2)))
        >>> planar = Positions(np.arange(2), np.zeros((2, 2)))
        >>> smap.check_position_frames([planar, None])
        >>> latlon = Positions(np.arange(2), np.full((2, 2), 45.0), geographic=True)
        >>> smap.check_position_frames([latlon])
        Traceback (most recent call last):
            ...
        sprint_map.errors.InputError: latitude/longitude positions given to a map of planar x, y
        positions: give x,y positions in the map's frame, or use another map
        >>> smap.close()
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
        The first fix of any of them chooses a new map's UTM zone. O(total rows).

        Parameters
        ----------
        tables : sequence of Positions or None
            The drives' positions, in drive order (None: a drive without).

        Returns
        -------
        list of (ndarray of float64, shape (n, 5)) or None
            One per table, as :meth:`metric_positions` gives it.

        Raises
        ------
        InputError
            Both frames among ``tables``, or the other frame than the map's; geographic
            positions without any fix.
        StorageIOError
            Storing the frame failed (nothing is stored); LMDB cannot be read.
        MapCorruptError
            A damaged map.

        Examples
        --------
        >>> import numpy as np
        >>> from sprint_map.examples import example_map
        >>> from sprint_map.frontend.positions import Positions
        >>> smap = example_map()
        >>> nofix = Positions(np.arange(1), np.full((1, 2), np.nan), geographic=True)
        >>> south = Positions(np.arange(1), np.array([[-33.87, 151.21]]), geographic=True)
        >>> [None if r is None else r.shape for r in smap.metric_positions_of([nofix, None, south])]
        [(1, 5), None, (1, 5)]
        >>> smap.geo_frame()  # chosen by the first fix: Sydney's
        GeoFrame(zone=56, south=True)
        >>> smap.metric_positions_of([Positions(np.arange(1), np.zeros((1, 2))), south])
        Traceback (most recent call last):
            ...
        sprint_map.errors.InputError: positions mix latitude/longitude and planar x, y: a map
        keeps one frame (give all drives lat,lon or all x,y)
        >>> smap.close()
        """
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

