"""Exports of a map for other tools: GraphML (networkx, Gephi), CSV (pandas), GeoJSON (QGIS).

Each export reads one consistent snapshot of the map
(:class:`~sprint_map.storage.scan.MapScan`, a read transaction: a writer may go on meanwhile),
streams it from the LMDB cursors without holding the graph (but for the sequence-level GraphML,
whose graph is small), and publishes every file atomically (``*.partial``, fsync,
``os.replace``; :mod:`sprint_map.util.output`): a reader of the output sees the old file or
the whole new one; a special file (a FIFO, ``/dev/stdout``) is written in place; a path inside
the map is refused. The formats are
written by networkx and the standard library (``csv``, ``json``, ``xml.sax.saxutils``); see
:mod:`~sprint_map.export.graphml`, :mod:`~sprint_map.export.tables`,
:mod:`~sprint_map.export.geojson`, and :mod:`~sprint_map.export.report` for the level rule.

Used through the facade (``SprintMap.export_graphml``, ``export_csv``, ``export_geojson``) and
``sprint-map export``.
"""

from __future__ import annotations

import contextlib
import io
import os
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

from sprint_map.errors import InputError
from sprint_map.export.geojson import has_positions, write_geojson
from sprint_map.export.graphml import write_sequence_graphml, write_vertex_graphml
from sprint_map.export.report import LEVELS, VERTEX_LEVEL_LIMIT, ExportReport, choose_level
from sprint_map.export.tables import TABLES, write_table
from sprint_map.storage.scan import MapScan
from sprint_map.storage.store import MapStore
from sprint_map.util.output import Output, commit_all, inside


def _text(out: Output) -> io.TextIOWrapper:
    """A UTF-8 text stream over ``out`` (a character UTF-8 cannot encode, a lone surrogate in
    a drive's free-text ``source``, becomes ``?``); flushed, not closed, by the caller."""
    return io.TextIOWrapper(out.stream, encoding="utf-8", errors="replace", newline="",
                            write_through=True)


def _write_text(out: Output, write: Callable[[IO[str]], Any]) -> None:
    text = _text(out)
    write(text)
    text.flush()
    text.detach()  # the Output owns (and closes) the binary stream


def export_graphml(store: MapStore, path: str | os.PathLike[str], level: str | None = None
                   ) -> ExportReport:
    """Write the map as GraphML at ``level`` (default: by size, see
    :func:`~sprint_map.export.report.choose_level`).

    Notes
    -----
    Vertex level: O(V + E) time, memory of one chunk (streamed). Sequence level: O(V + E)
    time, O(S + drive pairs) memory.
    """
    started = time.monotonic()
    with Output(path, "GraphML", forbidden=[store.path]) as out, MapScan(store) as scan:
        chosen = choose_level(level, scan.vertices)
        if chosen == "vertex":
            counts = (0, 0)

            def write(text: IO[str]) -> None:
                nonlocal counts
                counts = write_vertex_graphml(scan, text)

            _write_text(out, write)
        else:
            counts = write_sequence_graphml(scan, out.stream)
        size = out.stream.tell() if out.stream.seekable() else 0
        out.commit()
        sequences = len(scan.sequences)
    return ExportReport("graphml", str(out.asked), chosen, sequences, counts[0], counts[1],
                        size, round(time.monotonic() - started, 3))


def export_csv(store: MapStore, directory: str | os.PathLike[str]) -> ExportReport:
    """Write ``sequences.csv``, ``vertices.csv`` and ``edges.csv`` into ``directory`` (made if
    absent; files of those names are replaced), as one unit: all three are written before
    the first is published (:func:`~sprint_map.util.output.commit_all`). O(V + E) time, O(S)
    memory."""
    root = Path(directory)
    if root.exists() and not root.is_dir():
        raise InputError(f"{root} is not a directory: give a directory for the CSV files")
    if inside(Path(os.path.realpath(root)), store.path):
        raise InputError(f"{root} is inside the map {store.path}: write the CSV files outside "
                         "the map directory")
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot make {root}: {exc.strerror or exc}") from exc
    started = time.monotonic()
    rows: dict[str, int] = {}
    sizes: dict[str, int] = {}
    with contextlib.ExitStack() as stack, MapScan(store) as scan:
        outputs = [stack.enter_context(Output(root / name, "CSV", forbidden=[store.path]))
                   for name, _, _ in TABLES]
        for out, (name, columns, source) in zip(outputs, TABLES, strict=True):
            def write(text: IO[str], columns: tuple[str, ...] = columns,
                      source: Callable[[MapScan], Iterator[tuple[Any, ...]]] = source,
                      name: str = name) -> None:
                rows[name] = write_table(text, columns, source(scan))

            _write_text(out, write)
            sizes[name] = out.stream.tell() if out.stream.seekable() else 0
        commit_all(outputs)
        sequences = len(scan.sequences)
    files = [str(root / name) for name, _, _ in TABLES]
    return ExportReport("csv", str(root), None, sequences, rows["vertices.csv"],
                        rows["edges.csv"], sum(sizes.values()),
                        round(time.monotonic() - started, 3), files)


def export_geojson(store: MapStore, path: str | os.PathLike[str]) -> ExportReport:
    """Write the drives and edges that have positions as GeoJSON.

    Raises
    ------
    InputError
        No drive of the map has positions (nothing is written).
    """
    started = time.monotonic()
    counts = (0, 0, 0)
    with Output(path, "GeoJSON", forbidden=[store.path]) as out, MapScan(store) as scan:
        if not has_positions(scan):
            raise InputError("the map has no positions: GeoJSON needs drives ingested with "
                             "--positions (export --csv or --graphml instead)")

        def write(text: IO[str]) -> None:
            nonlocal counts
            counts = write_geojson(scan, text, store.path.name)

        _write_text(out, write)
        size = out.stream.tell() if out.stream.seekable() else 0
        out.commit()
        sequences = len(scan.sequences)
    return ExportReport("geojson", str(out.asked), None, sequences, counts[0], counts[1],
                        size, round(time.monotonic() - started, 3), skipped_edges=counts[2])


__all__ = ["LEVELS", "VERTEX_LEVEL_LIMIT", "ExportReport", "choose_level", "export_csv",
           "export_geojson", "export_graphml"]
