"""Summarising a map: which stored vertices are redundant, and what stands for them.

``sprint-map summarize MAP`` shrinks a map that kept everything (or any map) to what admission
``novel`` would have stored (:mod:`sprint_map.merge.admission`), after the fact. Sequences are
visited in commit order; a vertex ``v`` of sequence ``S`` is **redundant** when

1. an edge joins it to a vertex of an older sequence (a merge certified the place, the way
   admission asks the merge rule to have merged a frame), and
2. at least ``per_place`` older drives hold a kept view of that place that looks like it:
   among the vertices such an edge reaches, the older vertices joined by an edge to those,
   (for each that was itself dropped, the vertex standing for it) and up to two images either
   side on their sequences, kept views of at least ``per_place`` sequences are within
   ``max_step_ratio`` times ``S``'s median squared step between consecutive frames of ``v``
   (the scale of "alike" admission uses), and
3. retrieval still finds the place without it: among the ``NEIGHBOURS`` (32) nearest
   descriptors of ``v``, the nearest kept view of an older drive is one of the place's views.

So a place keeps at most ``per_place`` views per appearance, a view under an appearance no
kept view has stays, and so does one whose nearest older neighbour lies elsewhere (a view that
keeps retrieval right on a lookalike street).

The redundant frames of each sequence are smoothed as admission smooths a drive (stored runs
shorter than ``min_run`` dropped, redundant stretches shorter than ``min_skip`` kept, a margin
kept either side of each kept run), using the map's admission numbers. A dropped vertex's
**stand-in** is its nearest alike kept view: the summary
(:mod:`sprint_map.storage.reduction`) moves the dropped vertex's edges onto it, counts a
sighting of it, and stitches each kept run into the places the dropped stretches before and
after it were matched to.

Only older sequences' views can stand in, and an older sequence is decided before a newer one,
so a stand-in is always kept. The first drive of every place is never dropped.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from sprint_map.merge.admission import Admission, drive_step, runs, stored_mask
from sprint_map.storage.provenance import edge_table
from sprint_map.storage.records import EdgeRecord, SequenceRecord
from sprint_map.storage.reduction import Reduction

if TYPE_CHECKING:
    from sprint_map.storage.store import MapStore

__all__ = ["SummaryPlan", "plan_summary"]

#: Images either side of a reached vertex that count as views of its place.
RADIUS = 2
#: Nearest neighbours searched per view for the retrieval test.
NEIGHBOURS = 32


@dataclass(frozen=True)
class SummaryPlan:
    """What :func:`plan_summary` decided: the reduction, and per sequence the frames kept."""

    reduction: Reduction
    #: seq_id -> frames kept (every live sequence)
    kept: dict[int, int] = field(default_factory=dict)
    #: seq_id -> frames before
    frames: dict[int, int] = field(default_factory=dict)

    @property
    def vertices_before(self) -> int:
        return sum(self.frames.values())

    @property
    def vertices_after(self) -> int:
        return sum(self.kept.values())

    def to_dict(self) -> dict[str, Any]:
        return {"vertices_before": self.vertices_before, "vertices_after": self.vertices_after,
                "sequences_before": len(self.frames),
                "sequences_after": sum(1 for n in self.kept.values() if n),
                "stitches": len(self.reduction.stitches),
                "sightings": len(self.reduction.sightings)}


class _Summariser:
    """The state :func:`plan_summary` walks the sequences with: which vertices are kept so far
    (older sequences are final), the stand-ins, and the edges as a sorted adjacency."""

    def __init__(self, store: MapStore, per_place: int, admission: Admission) -> None:
        self.store = store
        self.per_place = per_place
        self.admission = admission
        self.seqs = sorted(store.sequences(), key=lambda s: s.first_vertex)
        self.total = store.counter("next_vertex_id")
        self.keep = np.zeros(self.total, dtype=bool)
        for s in self.seqs:
            self.keep[s.first_vertex:s.last_vertex + 1] = True
        self.redirect = np.full(self.total, -1, dtype=np.int64)
        self.starts = np.array([s.first_vertex for s in self.seqs], dtype=np.int64)
        table = edge_table(store)  # arrays, not an object per edge
        src, dst, weight = table.src, table.dst, table.prob
        ends = np.concatenate([src, dst])  # both directions, sorted by the first end
        order = np.argsort(ends, kind="stable")
        self.vertex = ends[order]
        self.neighbour = np.concatenate([dst, src])[order]
        self.weight = np.concatenate([weight, weight])[order]
        self.stitches: list[EdgeRecord] = []
        self.sightings: list[tuple[int, float, str, float]] = []
        self.now = time.time()

    def around(self, u: int) -> np.ndarray:
        """The vertices joined to ``u`` by an edge (either direction). O(log E)."""
        a, b = np.searchsorted(self.vertex, [u, u + 1])
        return self.neighbour[a:b]

    def place_views(self, reached: np.ndarray, first: int) -> np.ndarray:
        """The kept views of the place a vertex's edges to older drives ``reached`` name: those
        vertices and the older ones joined to them (a dropped one's stand-in instead), each
        with ``RADIUS`` images either side on its sequence. Sorted."""
        place = set(reached.tolist())
        for u in reached.tolist():
            place.update(w for w in self.around(u).tolist() if w < first)
        views: set[int] = set()
        for u in place:
            base = u if self.keep[u] else int(self.redirect[u])
            if base < 0:
                continue
            owner = self.seqs[int(np.searchsorted(self.starts, base, side="right")) - 1]
            lo = max(owner.first_vertex, base - RADIUS)
            hi = min(owner.last_vertex, base + RADIUS) + 1
            views.update(w for w in range(lo, hi) if self.keep[w])
        return np.array(sorted(views), dtype=np.int64)

    def stand_ins(self, seq: SequenceRecord, rows: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per image of ``seq``: the kept view standing for it if it is redundant (-1 if not),
        the squared distance to it, and the strongest weight of its edges to older drives."""
        stand = np.full(seq.length, -1, dtype=np.int64)
        dist = np.full(seq.length, np.inf)
        strength = np.zeros(seq.length)
        lo, hi = np.searchsorted(self.vertex, [seq.first_vertex, seq.last_vertex + 1])
        older = self.neighbour[lo:hi] < seq.first_vertex
        step = drive_step(rows)
        if not older.any() or not math.isfinite(step):
            return stand, dist, strength
        limit = self.admission.max_step_ratio * step
        ends, reached = self.vertex[lo:hi][older], self.neighbour[lo:hi][older]
        weights = self.weight[lo:hi][older]
        alike: list[tuple[int, np.ndarray, np.ndarray, float]] = []
        for v in np.unique(ends).tolist():
            mine = ends == v
            views = self.place_views(reached[mine], seq.first_vertex)
            i = v - seq.first_vertex
            if len(views) < self.per_place:
                continue
            diff = self.store.shards.take(views, self.total) - rows[i]
            d = np.einsum("ij,ij->i", diff, diff)
            # views of one drive count once: K views are K drives' views of the place
            drives = np.searchsorted(self.starts, views[d <= limit], side="right")
            if len(np.unique(drives)) >= self.per_place:
                alike.append((i, views, d, float(weights[mine].max())))
        if not alike:
            return stand, dist, strength
        # retrieval still finds the place without the image: the nearest kept view of an
        # older drive is one of the place's views (searched only for the alike images)
        _, hits = self.store.search(rows[[i for i, *_ in alike]], NEIGHBOURS)
        for (i, views, d, weight), row in zip(alike, hits, strict=True):
            row = row[(row >= 0) & (row < seq.first_vertex)]
            row = row[self.keep[row]]
            if len(row) and int(row[0]) in set(views.tolist()):
                stand[i], dist[i], strength[i] = views[int(np.argmin(d))], float(d.min()), weight
        return stand, dist, strength

    def summarise(self, seq: SequenceRecord) -> int:
        """Decide ``seq`` (every older sequence is decided); return the frames it keeps."""
        rows = np.asarray(self.store.descriptors(seq.seq_id), dtype=np.float32)
        stand, dist, strength = self.stand_ins(seq, rows)
        stored = stored_mask(stand >= 0, self.admission)
        if stored.all():
            return seq.length
        dropped = np.flatnonzero(~stored)
        self.keep[seq.first_vertex + dropped] = False
        self.redirect[seq.first_vertex + dropped] = stand[dropped]
        self.sightings.extend((int(stand[i]), float(dist[i]), seq.name, seq.created)
                              for i in dropped.tolist() if stand[i] >= 0)
        for a, b in runs(stored):
            if a > 0 and stand[a - 1] >= 0:  # in from the place the dropped stretch reached
                self.stitches.append(EdgeRecord(int(stand[a - 1]), seq.first_vertex + a,
                                                min(1.0, strength[a - 1]), seq.seq_id, None,
                                                self.now))
            if b < seq.length and stand[b] >= 0:  # out to the place the next one starts at
                self.stitches.append(EdgeRecord(seq.first_vertex + b - 1, int(stand[b]),
                                                min(1.0, strength[b]), seq.seq_id, None,
                                                self.now))
        return int(stored.sum())


def plan_summary(store: MapStore, per_place: int = 1, admission: Admission | None = None
                 ) -> SummaryPlan:
    """Decide which vertices of ``store`` a summary drops (see the module docstring).

    ``admission``: the ratio and smoothing numbers (the map's own; its ``mode`` is ignored).

    Raises
    ------
    ValueError
        ``per_place`` below 1.

    Notes
    -----
    O(E log E) for the edges; per vertex with an edge to an older drive, O(C * dim) distances
    to the C views of its place (its edges within two hops, 5 images each) and one
    ``NEIGHBOURS``-nearest search; one read of every sequence's rows.
    """
    if not isinstance(per_place, int) or per_place < 1:
        raise ValueError("per_place must be an integer >= 1")
    walk = _Summariser(store, per_place, admission if admission is not None else Admission())
    kept = {s.seq_id: walk.summarise(s) for s in walk.seqs}
    return SummaryPlan(Reduction(walk.keep, walk.redirect, walk.stitches, walk.sightings),
                       kept, {s.seq_id: s.length for s in walk.seqs})
