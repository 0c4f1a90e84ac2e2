"""Exports of a map for other tools: GraphML (networkx, Gephi), CSV (pandas), GeoJSON (QGIS).

Each export reads one consistent snapshot of the map
(:class:`~sprint_map.storage.scan.MapScan`, a read transaction: a writer may go on meanwhile),
streams it from the LMDB cursors without holding the graph (but for the sequence-level GraphML,
whose graph is small), and publishes every file atomically (``*.partial``, fsync,
``os.replace``): a reader of the output sees the old file or the whole new one. The formats are
written by networkx and the standard library (``csv``, ``json``, ``xml.sax.saxutils``); see
:mod:`~sprint_map.export.graphml`, :mod:`~sprint_map.export.tables`,
:mod:`~sprint_map.export.geojson`, and :mod:`~sprint_map.export.report` for the level rule.

Used through the facade (``SprintMap.export_graphml``, ``export_csv``, ``export_geojson``) and
``sprint-map export``.
"""

from __future__ import annotations

import contextlib
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
from sprint_map.util.atomic import PARTIAL_SUFFIX, publish


def _publish(path: Path, fill: Callable[[Path], None]) -> None:
    """:func:`~sprint_map.util.atomic.publish` ``path``; whatever fails the write (an I/O
    error, a corrupt record met half-way), the temporary file goes with it."""
    try:
        publish(path, fill)
    except BaseException:
        with contextlib.suppress(OSError):
            path.with_name(path.name + PARTIAL_SUFFIX).unlink(missing_ok=True)
        raise


def _publish_text(path: Path, write: Callable[[IO[str]], None]) -> None:
    """Publish ``path`` atomically, its text written by ``write(stream)`` (UTF-8; a character
    UTF-8 cannot encode, a lone surrogate in a drive's free-text ``source``, becomes ``?``)."""

    def fill(partial: Path) -> None:
        with open(partial, "w", encoding="utf-8", errors="replace", newline="") as out:
            write(out)

    _publish(path, fill)


def _target(path: str | os.PathLike[str], what: str) -> Path:
    target = Path(path)
    if target.is_dir():
        raise InputError(f"{target} is a directory: give the {what} file to write")
    if not target.parent.is_dir():
        raise InputError(f"{target.parent} is not a directory: cannot write {target.name}")
    return target


def export_graphml(store: MapStore, path: str | os.PathLike[str], level: str | None = None
                   ) -> ExportReport:
    """Write the map as GraphML at ``level`` (default: by size, see
    :func:`~sprint_map.export.report.choose_level`).

    Notes
    -----
    Vertex level: O(V + E) time, memory of one chunk (streamed). Sequence level: O(V + E)
    time, O(S + drive pairs) memory.
    """
    target = _target(path, "GraphML")
    started = time.monotonic()
    with MapScan(store) as scan:
        chosen = choose_level(level, scan.vertices)
        counts = (0, 0)

        def write(out: IO[str]) -> None:
            nonlocal counts
            counts = write_vertex_graphml(scan, out)

        if chosen == "vertex":
            _publish_text(target, write)
        else:
            def fill(partial: Path) -> None:
                nonlocal counts
                counts = write_sequence_graphml(scan, partial)

            _publish(target, fill)
        sequences = len(scan.sequences)
    return ExportReport("graphml", str(target), chosen, sequences, counts[0], counts[1],
                        target.stat().st_size, round(time.monotonic() - started, 3))


def export_csv(store: MapStore, directory: str | os.PathLike[str]) -> ExportReport:
    """Write ``sequences.csv``, ``vertices.csv`` and ``edges.csv`` into ``directory`` (made if
    absent; files of those names are replaced). O(V + E) time, O(S) memory."""
    root = Path(directory)
    if root.exists() and not root.is_dir():
        raise InputError(f"{root} is not a directory: give a directory for the CSV files")
    root.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    rows: dict[str, int] = {}
    with MapScan(store) as scan:
        for name, columns, source in TABLES:
            def write(out: IO[str], columns: tuple[str, ...] = columns,
                      source: Callable[[MapScan], Iterator[tuple[Any, ...]]] = source,
                      name: str = name) -> None:
                rows[name] = write_table(out, columns, source(scan))

            _publish_text(root / name, write)
        sequences = len(scan.sequences)
    files = [str(root / name) for name, _, _ in TABLES]
    return ExportReport("csv", str(root), None, sequences, rows["vertices.csv"],
                        rows["edges.csv"], sum(Path(f).stat().st_size for f in files),
                        round(time.monotonic() - started, 3), files)


def export_geojson(store: MapStore, path: str | os.PathLike[str]) -> ExportReport:
    """Write the drives and edges that have positions as GeoJSON.

    Raises
    ------
    InputError
        No drive of the map has positions (nothing is written).
    """
    target = _target(path, "GeoJSON")
    started = time.monotonic()
    counts = (0, 0, 0)
    with MapScan(store) as scan:
        if not has_positions(scan):
            raise InputError("the map has no positions: GeoJSON needs drives ingested with "
                             "--positions (export --csv or --graphml instead)")

        def write(out: IO[str]) -> None:
            nonlocal counts
            counts = write_geojson(scan, out, store.path.name)

        _publish_text(target, write)
        sequences = len(scan.sequences)
    return ExportReport("geojson", str(target), None, sequences, counts[0], counts[1],
                        target.stat().st_size, round(time.monotonic() - started, 3),
                        skipped_edges=counts[2])


__all__ = ["LEVELS", "VERTEX_LEVEL_LIMIT", "ExportReport", "choose_level", "export_csv",
           "export_geojson", "export_graphml"]
