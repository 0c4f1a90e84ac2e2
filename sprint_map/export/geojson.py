"""GeoJSON export: drives as LineStrings on their positions, merged edges as segments.

One ``FeatureCollection`` (RFC 7946) for QGIS and web maps:

- each live drive with positions is a ``LineString`` through its frames' ``[x, y]`` in frame
  order (a ``Point`` for a one-frame drive), with ``kind: "drive"``, ``seq_id``, ``name``,
  ``frames``, ``component``;
- each edge whose two endpoints have positions is a two-point ``LineString`` from the source
  frame to the target frame, with ``kind: "edge"``, ``src_seq``, ``src_image``, ``dst_seq``,
  ``dst_image``, ``prob``, ``added_by``, ``frame``. A match merged both ways is two directed
  edges; it is drawn once, from the smaller vertex, with ``both_ways: true``.

Coordinates: a map given latitude/longitude (``lat,lon`` positions, a bag's NavSatFix) keeps
them in one UTM zone (:class:`sprint_map.util.geo.GeoFrame`) and is written back in WGS84
longitude/latitude, as RFC 7946 wants. A map of planar positions is written with its ``x, y``
exactly as given to ``ingest --positions`` (usually metres in a local frame): in QGIS assign the
layer the CRS the positions were recorded in. A member ``sprint_map`` of the collection says
which, and counts the edges left out (an endpoint without a position). Frames without a fix
are left out of their drive's line.

Written with the standard library's ``json``: the collection's frame, then each feature as
``json.dumps`` of a dict, one per line, streamed from the LMDB cursors of one snapshot (one
drive's positions at a time, and one position look-up per edge end: O(E log V)).
"""

from __future__ import annotations

import itertools
import json
from collections.abc import Iterator
from typing import IO, Any

import numpy as np

from sprint_map.errors import InputError
from sprint_map.storage.scan import MapScan
from sprint_map.util.geo import GeoFrame

COORDINATES_NOTE = ("x, y as given to ingest --positions (not WGS84 unless they were recorded "
                    "so); assign the layer the CRS of the positions")
WGS84_NOTE = "WGS84 longitude, latitude (the map keeps them in UTM zone {zone}{hemi}, EPSG:{epsg})"


def map_frame(scan: MapScan) -> GeoFrame | None:
    """The map's geographic frame, or None for planar positions. O(1)."""
    record = scan.store.geo_frame()
    return None if record is None else GeoFrame.from_dict(record)


def _coords(xy: np.ndarray, frame: GeoFrame | None) -> list[list[float]]:
    """``[x, y]`` (or ``[lon, lat]`` with a geographic ``frame``) of the rows with a fix."""
    xy = xy[np.isfinite(xy).all(axis=1)]
    if frame is not None and len(xy):
        xy = frame.unproject(xy[:, 0], xy[:, 1])
    return [[x, y] for x, y in xy.tolist()]


def drive_features(scan: MapScan, frame: GeoFrame | None = None) -> Iterator[dict[str, Any]]:
    """Each drive with positions as a LineString (a Point for one fix)."""
    for seq, pos in scan.positions():
        if pos is None:
            continue
        coords = _coords(pos[:, :2], frame)
        if not coords:
            continue
        geometry = ({"type": "Point", "coordinates": coords[0]} if len(coords) == 1
                    else {"type": "LineString", "coordinates": coords})
        yield {"type": "Feature", "geometry": geometry,
               "properties": {"kind": "drive", "seq_id": seq.seq_id, "name": seq.name,
                              "frames": seq.length,
                              "component": scan.component.get(seq.seq_id, seq.seq_id)}}


def edge_features(scan: MapScan, skipped: list[int], frame: GeoFrame | None = None
                  ) -> Iterator[dict[str, Any]]:
    """Each edge between placed frames as a segment (a both-ways match once); the (directed)
    edges left out for want of a position are counted in ``skipped[0]``."""
    for src, dst, e in scan.edges():
        a, b = scan.position(src), scan.position(dst)
        if a is None or b is None:
            skipped[0] += 1
            continue
        both = scan.has_edge(dst, src)
        if both and dst < src:
            continue  # drawn with its reverse
        ends = np.array([a[:2], b[:2]])
        yield {"type": "Feature",
               "geometry": {"type": "LineString", "coordinates": _coords(ends, frame)},
               "properties": {"kind": "edge", "src_seq": e.src_seq, "src_image": e.src_image,
                              "dst_seq": e.dst_seq, "dst_image": e.dst_image, "prob": e.prob,
                              "added_by": e.added_by, "frame": e.frame, "both_ways": both}}


def has_positions(scan: MapScan) -> bool:
    """Whether any live drive has positions. O(sequences) cursor seeks at worst."""
    return any(scan.has_position(seq.first_vertex, seq.last_vertex) for seq in scan.sequences)


def write_geojson(scan: MapScan, out: IO[str], name: str) -> tuple[int, int, int]:
    """Stream the collection to the text stream ``out``; return (drives, edges, edges left out).

    Raises
    ------
    InputError
        No drive of the map has positions (there is nothing to place).

    Notes
    -----
    O(V + E log V) time; memory of one drive's coordinates.
    """
    if not has_positions(scan):
        raise InputError("the map has no positions: GeoJSON needs drives ingested with "
                         "--positions (export --csv or --graphml instead)")
    out.write('{"type": "FeatureCollection", "name": ')
    out.write(json.dumps(name))
    out.write(', "features": [\n')
    counts = {"drive": 0, "edge": 0}
    skipped = [0]
    first = True
    frame = map_frame(scan)
    for feature in itertools.chain(drive_features(scan, frame),
                                   edge_features(scan, skipped, frame)):
        if not first:
            out.write(",\n")
        first = False
        out.write(json.dumps(feature))
        counts[feature["properties"]["kind"]] += 1
    out.write('\n], "sprint_map": ')
    note = COORDINATES_NOTE if frame is None else WGS84_NOTE.format(
        zone=frame.zone, hemi="S" if frame.south else "N", epsg=frame.epsg)
    out.write(json.dumps({"coordinates": note, "crs": None if frame is None else "EPSG:4326",
                          "edges_without_positions": skipped[0]}))
    out.write("}\n")
    return counts["drive"], counts["edge"], skipped[0]


__all__ = ["COORDINATES_NOTE", "WGS84_NOTE", "drive_features", "edge_features", "has_positions",
           "map_frame", "write_geojson"]
