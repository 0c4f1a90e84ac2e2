"""CSV export: three tables for pandas, spreadsheets and databases, streamed row by row.

``DIR/sequences.csv``: ``seq_id, name, frames, component, source, created``;
``DIR/vertices.csv``: ``seq_id, image_id, x, y, heading, timestamp`` (one row per live frame; a
field is empty where the map does not know it); ``DIR/edges.csv``: ``src_seq, src_image,
dst_seq, dst_image, prob, added_by, frame, time`` (one row per directed edge; ``added_by`` and
``frame`` empty when unknown). Written with the standard library's ``csv`` module (RFC 4180
quoting, UTF-8, a header row), the three files as one unit, each atomically (:mod:`sprint_map.util.output`).
Floats are written as Python's shortest round-trip ``repr``.

**Formula injection.** A spreadsheet runs a cell that starts with ``=``, ``+``, ``-`` or
``@`` as a formula (``=HYPERLINK(...)``, ``=cmd|...``). The two free-text columns, ``name`` and
``source``, hold what a user typed, so a text cell that starts with one of those, a tab, a
carriage return or an apostrophe is written with an apostrophe first (:func:`text_cell`, the
OWASP rule): a spreadsheet shows it as text, and :func:`read_text_cell` (drop one leading
apostrophe) gives the name back exactly. Numbers are never escaped.

Rows stream from the LMDB cursors of one snapshot (:class:`~sprint_map.storage.scan.MapScan`):
memory is one drive's positions or one batch of edges, never the graph.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterator
from typing import IO, Any

from sprint_map.storage.scan import MapScan

SEQUENCE_COLUMNS = ("seq_id", "name", "frames", "component", "source", "created")
VERTEX_COLUMNS = ("seq_id", "image_id", "x", "y", "heading", "timestamp", "sigma_m")
EDGE_COLUMNS = ("src_seq", "src_image", "dst_seq", "dst_image", "prob", "added_by", "frame",
                "time")


#: First characters that make a spreadsheet read a cell as a formula, and the escape itself.
FORMULA_START = ("=", "+", "-", "@", "\t", "\r", "'")


def text_cell(text: str) -> str:
    """``text`` as a CSV cell no spreadsheet runs: an apostrophe is put before one that starts
    with a formula character (:data:`FORMULA_START`). O(1)."""
    return "'" + text if text.startswith(FORMULA_START) else text


def read_text_cell(cell: str) -> str:
    """The text a :func:`text_cell` cell holds (its leading apostrophe, if any, removed)."""
    return cell[1:] if cell.startswith("'") else cell


def _cell(value: float) -> float | str:
    return "" if math.isnan(value) else value


def sequence_rows(scan: MapScan) -> Iterator[tuple[Any, ...]]:
    for seq in scan.sequences:
        yield (seq.seq_id, text_cell(seq.name), seq.length,
               scan.component.get(seq.seq_id, seq.seq_id), text_cell(seq.source), seq.created)


def vertex_rows(scan: MapScan) -> Iterator[tuple[Any, ...]]:
    for seq, pos in scan.positions():
        if pos is None:
            for image in range(seq.length):
                yield seq.seq_id, image, "", "", "", "", ""
            continue
        for image, row in enumerate(pos.tolist()):
            yield (seq.seq_id, image, *(_cell(value) for value in row))


def edge_rows(scan: MapScan) -> Iterator[tuple[Any, ...]]:
    for _, _, e in scan.edges():
        yield (e.src_seq, e.src_image, e.dst_seq, e.dst_image, e.prob,
               "" if e.added_by is None else e.added_by, "" if e.frame is None else e.frame,
               e.time)


#: File name, header and row source of each table, in the order they are written.
TABLES = (("sequences.csv", SEQUENCE_COLUMNS, sequence_rows),
          ("vertices.csv", VERTEX_COLUMNS, vertex_rows),
          ("edges.csv", EDGE_COLUMNS, edge_rows))


def write_table(out: IO[str], columns: tuple[str, ...], rows: Iterator[tuple[Any, ...]]) -> int:
    """Write a header and ``rows`` to the text stream ``out`` (opened with ``newline=""``);
    return the number of rows. O(rows) time, O(1) memory."""
    writer = csv.writer(out)
    writer.writerow(columns)
    count = 0
    for row in rows:
        writer.writerow(row)
        count += 1
    return count


__all__ = ["EDGE_COLUMNS", "FORMULA_START", "SEQUENCE_COLUMNS", "TABLES", "VERTEX_COLUMNS",
           "edge_rows", "read_text_cell", "sequence_rows", "text_cell", "vertex_rows",
           "write_table"]
