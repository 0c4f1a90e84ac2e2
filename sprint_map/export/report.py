"""What an export wrote, and which graph level a GraphML export takes by default.

**The level rule.** A map of at most :data:`VERTEX_LEVEL_LIMIT` (100,000) live vertices is
exported at the vertex level by default (one node per frame), a larger one at the sequence level
(one node per drive, one edge per pair of drives with their match counts). The vertex level is
still written for any size on request (``--level vertex``) and always streams, so the *writer's*
memory is bounded either way (``docs/benchmarks.md``, "Export"); the limit is about the *reader*:
``networkx.read_graphml`` (and Gephi, Cytoscape) build the whole document and graph in memory,
about 4.7 KB per vertex (573 MB to read 100k vertices back): some 5 GB at 1M, where a
sequence-level graph of the same map is a few megabytes (2.4 MB for 1,000 drives) and shows
what a person looks at a whole map for (which drives were merged with which). See
``docs/export.md``.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

from sprint_map.errors import InputError

#: Graph levels of a GraphML export.
LEVELS = ("vertex", "sequence")
#: Largest map (live vertices) exported at the vertex level by default.
VERTEX_LEVEL_LIMIT = 100_000


def choose_level(level: str | None, vertices: int) -> str:
    """The level of a GraphML export: ``level`` if given, else by :data:`VERTEX_LEVEL_LIMIT`.

    Raises
    ------
    InputError
        ``level`` is not one of :data:`LEVELS`.
    """
    if level is None:
        return "vertex" if vertices <= VERTEX_LEVEL_LIMIT else "sequence"
    if level not in LEVELS:
        raise InputError(f"export level must be one of {', '.join(LEVELS)}, not {level!r}")
    return level


@dataclass(frozen=True)
class ExportReport:
    """What one export wrote (the JSON of ``sprint-map export --json`` is a list of these).

    ``nodes`` and ``edges`` are the graph's (GraphML), the rows (CSV: vertices, edges) or the
    features (GeoJSON: drives as lines, edges as segments); ``skipped_edges`` counts the edges
    a GeoJSON export left out because an endpoint has no position.
    """

    format: str
    path: str
    level: str | None
    sequences: int
    nodes: int
    edges: int
    bytes: int
    seconds: float
    files: list[str] = field(default_factory=list)
    skipped_edges: int = 0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


__all__ = ["LEVELS", "VERTEX_LEVEL_LIMIT", "ExportReport", "choose_level"]
