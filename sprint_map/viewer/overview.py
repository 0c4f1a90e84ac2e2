"""The viewer's overview of a map, summarised server-side so that its size does not follow the map.

Level of detail, so that the page stays responsive at a million vertices:

* drives are polylines on their positions, decimated to a total of ``point_budget`` points
  (each drive keeps a share proportional to its length, at least its two ends), quantised to a
  16-bit grid over the map's bounding box;
* edges are drawn one by one while the map has at most ``edge_budget`` of them; beyond, they
  are aggregated per pair of sequences (count, mean probability) and each pair is drawn as a
  few representative segments (spread over the pair's edges);
* a map without positions is drawn as a layout of its sequence graph (networkx
  ``spring_layout`` weighted by the edges between sequences; components apart on a grid when
  there are too many sequences for it): each drive a node, each pair one segment.

The overview is computed once per map state (the map's counts, which every change moves) and
kept; reading goes through a ``read`` callable so a server can run each short read under
its map gate.
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

if TYPE_CHECKING:
    from sprint_map import SequenceRecord
    from sprint_map.map import SprintMap

__all__ = ["EDGE_BUDGET", "POINT_BUDGET", "MapState", "MapOverview", "Reader", "direct"]

T = TypeVar("T")
#: Runs one short read of the map (``direct``: just calls it; the server: under its gate).
Reader = Callable[[Callable[[], T]], T]

#: Polyline points sent for the whole overview (about 12 bytes of JSON each).
POINT_BUDGET = 50_000
#: Edges drawn one by one up to this many; beyond, aggregated per sequence pair.
EDGE_BUDGET = 5_000
#: Representative segments drawn per sequence pair when edges are aggregated (at most).
SEGMENTS_PER_PAIR = 3
#: Segments drawn in all when edges are aggregated (about 24 bytes of JSON each).
SEGMENT_BUDGET = 10_000
#: Sequence pairs listed, the most connected first (the rest are counted in ``total``).
PAIR_BUDGET = 5_000
#: Sequences beyond which the layout places components on a grid, not by spring layout.
SPRING_MAX = 1_500
#: Quantisation grid of the coordinates sent (0 .. GRID).
GRID = 65_535


def direct(fn: Callable[[], T]) -> T:
    """The :data:`Reader` of a process that owns its map (``sprint-map view``)."""
    return fn()


@dataclass
class MapState:
    """The map as the viewer last read it: its drives, their components and positions.

    Take it once per request (:meth:`MapOverview.state`) and look drives up here: O(1) each.
    """

    key: tuple[Any, ...]
    seqs: list[SequenceRecord]
    components: dict[int, int]  # seq id -> component
    xy: dict[int, np.ndarray]  # seq id -> (n, 2) x, y (drives with positions)
    overview: dict[str, Any] = field(default_factory=dict)
    by_id: dict[int, SequenceRecord] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.by_id = {s.seq_id: s for s in self.seqs}

    def sequence(self, seq_id: int) -> SequenceRecord | None:
        return self.by_id.get(seq_id)

    def positions(self, seq_id: int) -> np.ndarray | None:
        """``(n, 2)`` positions of a drive, or None."""
        return self.xy.get(seq_id)

    def component(self, seq_id: int) -> int:
        return self.components[seq_id]


class MapOverview:
    """What the viewer knows of one map: its overview and per-drive positions, cached.

    Parameters
    ----------
    smap : SprintMap
    read : Reader
        How to run one short read of the map.

    Notes
    -----
    The first :meth:`overview` after a change costs O(V + E) (positions and edges read once,
    vectorised); later calls O(S) to check the map has not changed.
    """

    def __init__(self, smap: SprintMap, read: Reader[Any] = direct, *,
                 point_budget: int = POINT_BUDGET, edge_budget: int = EDGE_BUDGET) -> None:
        self.map = smap
        self.read = read
        self.point_budget = point_budget
        self.edge_budget = edge_budget
        self._state: MapState | None = None
        self._lock = threading.Lock()

    # --- state ---------------------------------------------------------------------------------
    def _key(self) -> tuple[Any, ...]:
        """What changes whenever what the viewer shows does: the map's counts. A commit adds
        vertices (ids are never reused), a removal takes sequences, an unmerge edges; a
        compaction renumbers vertices (fewer), which changes nothing shown but is seen too.
        O(1)."""
        return tuple(sorted(self.read(lambda: self.map.stats()).items()))

    def state(self) -> MapState:
        """The cached state, re-read if the map changed since (O(1) to check)."""
        key = self._key()
        with self._lock:
            if self._state is None or self._state.key != key:
                self._state = self._load(key)
            return self._state

    def _positions(self, seq_id: int) -> Any:
        return self.map.positions(seq_id)  # the map current when the read runs

    def _load(self, key: tuple[Any, ...]) -> MapState:
        seqs = self.read(lambda: self.map.sequences())
        component = {}
        for comp in self.read(lambda: self.map.components()):
            for s in comp.sequences:
                component[s] = comp.component
        positions = {}
        for s in seqs:
            pos = self.read(functools.partial(self._positions, s.seq_id))
            if pos is not None and np.isfinite(pos[:, :2]).all():
                positions[s.seq_id] = np.ascontiguousarray(pos[:, :2])
        return MapState(key, seqs, component, positions)

    # --- the overview --------------------------------------------------------------------------
    def overview(self) -> dict[str, Any]:
        """The overview's JSON (see the module notes); cached per map state."""
        state = self.state()
        with self._lock:
            if not state.overview:
                state.overview = self._overview(state)
            return state.overview

    def _overview(self, st: MapState) -> dict[str, Any]:
        info = self.read(lambda: self.map.info())
        table = self.read(lambda: self.map.edge_table())
        seqs = st.seqs
        first = np.array([s.first_vertex for s in seqs], np.int64)
        order = np.argsort(first)
        sorted_first = first[order]
        ids = np.array([s.seq_id for s in seqs], np.int64)

        def locate(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            pos = order[np.clip(np.searchsorted(sorted_first, v, side="right") - 1, 0, None)]
            return pos, v - first[pos]

        si, sim = locate(table.src) if len(seqs) else (table.src, table.src)
        di, dim_ = locate(table.dst) if len(seqs) else (table.dst, table.dst)
        mode = "positions" if st.xy else "layout"
        out: dict[str, Any] = {
            "version": 1,
            "mode": mode,
            "counts": {k: info[k] for k in ("sequences", "vertices", "edges", "components")}
            | {"disk_bytes": info["disk_bytes"]},
            "path": info["path"],
            "sequences": {
                "id": ids.tolist(), "name": [s.name for s in seqs],
                "frames": [s.length for s in seqs],
                "component": [st.components[s.seq_id] for s in seqs],
                "positions": [s.seq_id in st.xy for s in seqs],
            },
        }
        # sequence pairs (unordered) and their edge counts
        a, b = np.minimum(si, di), np.maximum(si, di)
        n = max(len(seqs), 1)
        pair = a * n + b
        uniq, inverse, counts = np.unique(pair, return_inverse=True, return_counts=True)
        prob_sum = np.bincount(inverse, weights=table.prob, minlength=len(uniq))
        rank = np.argsort(-counts, kind="stable")
        listed = rank[:PAIR_BUDGET]
        out["pairs"] = {"a": ids[uniq[listed] // n].tolist(),
                        "b": ids[uniq[listed] % n].tolist(),
                        "edges": counts[listed].tolist(),
                        "mean_prob": np.round(prob_sum[listed] / counts[listed], 3).tolist(),
                        "total": len(uniq)}
        if mode == "positions":
            out |= self._drawn_positions(st, seqs, ids, (si, sim, di, dim_), inverse, rank)
        else:
            out |= self._drawn_layout(st, seqs, uniq, counts, n)
        return out

    def _drawn_positions(self, st: MapState, seqs: list[SequenceRecord], ids: np.ndarray,
                         ends: tuple[np.ndarray, ...], inverse: np.ndarray, rank: np.ndarray
                         ) -> dict[str, Any]:
        xy_all = [p for p in st.xy.values()]
        lo = np.min([p.min(axis=0) for p in xy_all], axis=0)
        hi = np.max([p.max(axis=0) for p in xy_all], axis=0)
        span = float(max(hi[0] - lo[0], hi[1] - lo[1], 1e-9))

        def q(xy: np.ndarray) -> np.ndarray:
            out: np.ndarray = np.rint((xy - lo) / span * GRID).astype(np.int64)
            return out

        total = sum(len(p) for p in xy_all)
        counts, xs = [], []
        for s in seqs:
            p = st.xy.get(s.seq_id)
            if p is None:
                counts.append(0)
                continue
            keep = max(2, int(self.point_budget * len(p) / total))
            idx = np.unique(np.linspace(0, len(p) - 1, min(keep, len(p))).round().astype(int))
            xs.append(q(p[idx]).ravel())
            counts.append(len(idx))
        si, sim, di, dim_ = ends
        seg_mask = np.zeros(len(si), bool)
        if len(si) <= self.edge_budget:
            seg_mask[:] = True
            level = "vertex"
        else:  # a few per kept pair, spread over its edges
            level = "pair"
            n_pairs = int(inverse.max()) + 1 if len(inverse) else 0
            order = np.argsort(inverse, kind="stable")
            starts = np.searchsorted(inverse[order], np.arange(n_pairs))
            ends_ = np.r_[starts[1:], len(order)]
            per_pair = max(1, min(SEGMENTS_PER_PAIR, SEGMENT_BUDGET // max(len(rank), 1)))
            for p in rank[:SEGMENT_BUDGET].tolist():
                m = ends_[p] - starts[p]
                picks = np.unique(np.linspace(0, m - 1, min(per_pair, m)).astype(int))
                seg_mask[order[starts[p] + picks]] = True
        segs = []
        for e in np.flatnonzero(seg_mask).tolist():
            ps, pd = st.xy.get(int(ids[si[e]])), st.xy.get(int(ids[di[e]]))
            if ps is None or pd is None:
                continue
            segs.append(np.r_[ps[sim[e]], pd[dim_[e]]])
        seg_xy = q(np.array(segs).reshape(-1, 2)).ravel() if segs else np.empty(0, np.int64)
        return {
            "bbox": [float(lo[0]), float(lo[1]), float(lo[0] + span), float(lo[1] + span)],
            "grid": GRID,
            "points": counts,
            "xy": np.concatenate(xs).tolist() if xs else [],
            "edges": {"level": level, "xy": seg_xy.tolist(), "drawn": len(segs)},
        }

    def _drawn_layout(self, st: MapState, seqs: list[SequenceRecord], pairs: np.ndarray,
                      counts: np.ndarray, n: int) -> dict[str, Any]:
        import networkx as nx

        graph = nx.Graph()
        graph.add_nodes_from(range(len(seqs)))
        for p, c in zip(pairs.tolist(), counts.tolist(), strict=True):
            if p // n != p % n:
                graph.add_edge(p // n, p % n, weight=math.log1p(c))
        if len(seqs) <= SPRING_MAX:
            layout = nx.spring_layout(graph, seed=17, weight="weight") if len(seqs) else {}
            xy = np.array([layout[i] for i in range(len(seqs))]).reshape(-1, 2)
        else:  # components on a grid, each a circle of its sequences
            comps: dict[int, list[int]] = {}
            for i, s in enumerate(seqs):
                comps.setdefault(st.components[s.seq_id], []).append(i)
            side = math.ceil(math.sqrt(len(comps)))
            xy = np.zeros((len(seqs), 2))
            for c, (_, members) in enumerate(sorted(comps.items(), key=lambda kv: -len(kv[1]))):
                angle = np.linspace(0, 2 * np.pi, len(members), endpoint=False)
                r = 0.4 * min(1.0, math.sqrt(len(members)) / 10)
                xy[members] = np.c_[c % side + 0.5 + r * np.cos(angle),
                                    c // side + 0.5 + r * np.sin(angle)]
        lo = xy.min(axis=0) if len(xy) else np.zeros(2)
        span = float(max(np.ptp(xy, axis=0).max() if len(xy) else 1.0, 1e-9))
        grid = np.rint((xy - lo) / span * GRID).astype(np.int64)
        return {"bbox": [0.0, 0.0, 1.0, 1.0], "grid": GRID, "layout": grid.ravel().tolist()}
