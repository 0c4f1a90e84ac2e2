"""Per-frame decision: the most probable *place*, its belief mass, and novelty ("no match").

Where several drives cover the same street, the belief of the true place is split over their
vertices, so one vertex's posterior understates the confidence. The decision therefore scores a
few candidate vertices (the most probable ones) by the mass of their place:

    place(v) = N_r(v)  U  union of N_r(b) for every b joined to a vertex of N_r(v) by a path
               of at most h edges (either direction),

where ``N_r(v)`` is the images ``i - r .. i + r`` of v's sequence (``r = place_radius``,
``h = place_hops``). Paths follow edges only, never temporal moves, so a place does not drift
along the road when many drives are chained by their merge edges. The
union is taken over slot intervals (no vertex counts twice), so the place mass is a probability
in [0, 1]. The answer is the candidate with the largest place mass; it is "no match" when that
mass is below ``min_confidence`` or when the sink ("off the map") holds at least as much.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Container
from dataclasses import dataclass

import numpy as np

from sprint_map.hmm.graph import ComponentGraph

__all__ = ["BeliefView", "CANDIDATE_FLOOR", "Decision", "decide", "is_unknown", "place_contrast",
           "place_mass", "place_runs", "place_runs_np", "top_candidates", "top_positions"]

#: Relative belief below which a vertex is not a decision candidate (see top_candidates).
CANDIDATE_FLOOR = 1e-6


@dataclass(frozen=True, slots=True)
class Decision:
    """One frame's localisation answer.

    Attributes
    ----------
    vertex_id : int or None
        The matched global vertex id; None for "no match" (the map does not know the place).
    seq_id, image_id : int or None
        The same vertex as (sequence id, image index); None for "no match".
    prob : float
        Belief mass of the best place (in [0, 1]); reported for "no match" too.
    vertex_prob : float
        Posterior of the best candidate vertex alone.
    sink_prob : float
        Posterior of the sink ("off the map": new place, or past the end of a sequence).
    n_active_components, n_active_vertices : int
        Size of the active set after this frame.
    candidate_id : int or None
        The best candidate vertex even when the answer is "no match" (None if the belief is all
        in the sink).
    contrast : float
        How much the decided place stands out among the frame's hits (:func:`place_contrast`);
        set by the smoother's decisions, NaN otherwise (the causal filter does not compute it).
    """

    vertex_id: int | None
    seq_id: int | None
    image_id: int | None
    prob: float
    vertex_prob: float
    sink_prob: float
    n_active_components: int
    n_active_vertices: int
    candidate_id: int | None = None
    contrast: float = math.nan

    @property
    def is_match(self) -> bool:
        """Whether the frame was localised."""
        return self.vertex_id is not None


def is_unknown(mass: float, sink: float, min_confidence: float) -> bool:
    """The one rule for "no match": the best place holds less than ``min_confidence`` of the
    belief, or the unmapped place ("off the map") holds at least as much as it. The causal,
    lagged and smoothed answers all follow it (a smoothed decision with the drive's calibrated
    ``novel_prob`` as ``sink``: :meth:`FrameDecision.settled
    <sprint_map.localize.localizer.FrameDecision.settled>`). O(1).

    >>> is_unknown(0.9, 0.05, 0.2), is_unknown(0.6, 0.96, 0.2), is_unknown(0.1, 0.0, 0.2)
    (False, True, True)
    """
    return mass < min_confidence or sink >= mass


@dataclass(slots=True)
class BeliefView:
    """One component's belief in slot layout (what the decision code reads).

    ``x[slot_first[s] + image]`` is the belief of image ``image`` of sequence ``s`` (in
    ``graph.seq_ids`` order); other slots (gutters) hold 0. Only the *live* slots can hold
    belief: ``idx`` (ascending) if given, else the slice ``x[a:b]`` (``b = None``: all of ``x``).
    The posterior is ``x * scale`` (the filter normalises lazily).
    """

    graph: ComponentGraph
    slot_first: np.ndarray
    x: np.ndarray
    idx: np.ndarray | None = None
    a: int = 0
    b: int | None = None
    scale: float = 1.0

    def live(self) -> tuple[np.ndarray, np.ndarray | int]:
        """``(values, slots)`` of the live slots: ``slots`` is an index array or, for a slice,
        the slot of ``values[0]``."""
        if self.idx is not None:
            return self.x[self.idx], self.idx
        return self.x[self.a:self.b], self.a


#: Places reaching more vertices than this are computed with numpy set operations; smaller ones
#: (the common case) with Python sets, which cost far less per call at that size.
_PY_PLACE = 256


def place_runs(view: BeliefView, slot: int, radius: int, hops: int = 1
               ) -> list[tuple[int, int]]:
    """The place of the vertex at ``slot`` as disjoint slot runs ``[start, stop)``, ascending.

    Parameters
    ----------
    view : BeliefView
    slot : int
        Slot of the vertex.
    radius : int
        ``place_radius``.
    hops : int
        ``place_hops``: how many edges away from the vertex's neighbourhood the place reaches.

    Notes
    -----
    O(r + h d log d) for the d vertices reached over h hops; never touches the rest of the
    component. A vertex without edges near it costs a few scalar reads; a small place (up to
    ``_PY_PLACE`` vertices) is gathered with Python sets, a larger one with numpy set
    operations (same result).
    """
    graph = view.graph
    slot_first = view.slot_first
    s = 0 if len(slot_first) == 1 else int(np.searchsorted(slot_first, slot, side="right")) - 1
    first = int(slot_first[s])
    image = slot - first
    lo = max(image - radius, 0)
    hi = min(image + radius, int(graph.seq_len[s]) - 1)
    own = (first + lo, first + hi + 1)
    if not graph.n_edges or hops < 1:
        return [own]
    base = int(graph.local_first[s])
    indptr = graph.adj_indptr
    indices = graph.adj_indices
    seed_lo, seed_hi = base + lo, base + hi + 1
    p0, p1 = indptr.item(seed_lo), indptr.item(seed_hi)
    if p0 == p1:
        return [own]
    if p1 - p0 > _PY_PLACE:
        return place_runs_np(view, s, lo, hi, radius, hops)
    # Follow edges only (aligned frames), never temporal moves: the place does not drift
    # along the road however many drives are chained together.
    frontier = {v for v in indices[p0:p1].tolist() if not seed_lo <= v < seed_hi}
    if not frontier:
        return [own]
    visited = set(frontier)  # the seeds are the range [seed_lo, seed_hi)
    for _ in range(hops - 1):
        reached: set[int] = set()
        for v in frontier:
            a, b = indptr.item(v), indptr.item(v + 1)
            if a < b:
                reached.update(indices[a:b].tolist())
        reached = {v for v in reached if v not in visited and not seed_lo <= v < seed_hi}
        if not reached:
            break
        visited |= reached
        if len(visited) > _PY_PLACE:
            return place_runs_np(view, s, lo, hi, radius, hops)
        frontier = reached
    nb = np.fromiter(visited, dtype=np.int64, count=len(visited))
    nb_seq = np.searchsorted(graph.local_first, nb, side="right") - 1
    nb_image = (nb - graph.local_first[nb_seq]).tolist()
    nb_first = slot_first[nb_seq].tolist()
    nb_last = (graph.seq_len[nb_seq] - 1).tolist()
    spans = [(f + max(i - radius, 0), f + min(i + radius, last) + 1)
             for f, i, last in zip(nb_first, nb_image, nb_last, strict=True)]
    spans.append(own)
    spans.sort()
    # A new run starts where an interval begins after everything before it has ended.
    out = [list(spans[0])]
    for start, stop in spans[1:]:
        run = out[-1]
        if start < run[1]:
            if stop > run[1]:
                run[1] = stop
        else:
            out.append([start, stop])
    return [(a, b) for a, b in out]


def place_runs_np(view: BeliefView, s: int, lo: int, hi: int, radius: int, hops: int
                   ) -> list[tuple[int, int]]:
    """:func:`place_runs` with numpy set operations (large places): sequence ``s``, images
    ``lo .. hi`` of the vertex's neighbourhood."""
    graph = view.graph
    slot_first = view.slot_first
    first = int(slot_first[s])
    own = (first + lo, first + hi + 1)
    base = int(graph.local_first[s])
    indptr = graph.adj_indptr
    indices = graph.adj_indices
    seeds = np.arange(base + lo, base + hi + 1, dtype=np.int64)
    frontier = np.setdiff1d(indices[indptr[base + lo]: indptr[base + hi + 1]], seeds)
    if frontier.size == 0:
        return [own]
    visited = np.union1d(seeds, frontier)
    for _ in range(hops - 1):
        reached = np.setdiff1d(_csr_gather(indptr, indices, frontier), visited)
        if reached.size == 0:
            break
        visited = np.union1d(visited, reached)
        frontier = reached
    nb = np.setdiff1d(visited, seeds, assume_unique=True)
    nb_seq = np.searchsorted(graph.local_first, nb, side="right") - 1
    nb_image = nb - graph.local_first[nb_seq]
    nb_lo = np.maximum(nb_image - radius, 0)
    nb_hi = np.minimum(nb_image + radius, graph.seq_len[nb_seq] - 1)
    starts = np.append(slot_first[nb_seq] + nb_lo, own[0])
    stops = np.append(slot_first[nb_seq] + nb_hi + 1, own[1])
    order = np.argsort(starts, kind="stable")
    starts = starts[order]
    stops = np.maximum.accumulate(stops[order])
    new = np.empty(len(starts), dtype=bool)
    new[0] = True
    np.greater_equal(starts[1:], stops[:-1], out=new[1:])
    new_idx = np.flatnonzero(new)
    run_starts = starts[new_idx].tolist()
    run_stops = stops[np.append(new_idx[1:] - 1, len(starts) - 1)].tolist()
    return list(zip(run_starts, run_stops, strict=True))


def _csr_gather(indptr: np.ndarray, indices: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Concatenated adjacency lists of ``rows`` (vectorised)."""
    starts = indptr[rows]
    lengths = indptr[rows + 1] - starts
    offsets = np.cumsum(lengths) - lengths
    flat = np.arange(int(lengths.sum()), dtype=np.int64) + np.repeat(starts - offsets, lengths)
    out: np.ndarray = indices[flat]
    return out


def place_mass(view: BeliefView, slot: int, radius: int, hops: int = 1) -> float:
    """Belief mass of the place of the vertex at ``slot`` (see the module docstring).

    Notes
    -----
    Like :func:`place_runs`; each vertex of the place counts once.
    """
    return _runs_sum(view.x, place_runs(view, slot, radius, hops)) * view.scale


def place_contrast(view: BeliefView, slot: int, hit_ids: list[int], hit_dists: list[float],
                   radius: int, hops: int, reach: int,
                   rivals: Container[int] | None = None) -> float:
    """How much the place of the vertex at ``slot`` stands out among a frame's hits.

    The distance of the frame's best hit inside the place (:func:`place_runs` with ``radius``
    and ``hops``) over that of its best hit elsewhere (outside the place widened to ``reach``
    images, in any component): below 1 the place is the closest thing the map holds (Lowe's
    ratio test, for places). ``hit_ids``/``hit_dists``: the frame's distinct valid hits;
    ``rivals``, if given: the only hits that count as elsewhere (those the neighbouring frames
    confirm). Returns 0 when nothing was retrieved elsewhere, ``inf`` when no hit fell inside
    the place. O(k + r + h d log d) for k hits (two :func:`place_runs`).

    Examples
    --------
    >>> import numpy as np
    >>> from sprint_map.hmm import MemoryGraphSource
    >>> g = MemoryGraphSource([50, 50]).load_component(0)
    >>> view = BeliefView(g, np.array([0]), np.zeros(50))
    >>> place_contrast(view, 10, [10, 30], [0.1, 0.2], 2, 1, 5)  # 30 is elsewhere on the drive
    0.5
    >>> place_contrast(view, 10, [10, 13, 75], [0.1, 0.05, 0.4], 2, 1, 5)  # 13: surroundings
    0.25
    """
    if not hit_ids:
        return math.inf
    inner = _vertex_ranges(view, place_runs(view, slot, radius, hops))
    outer = _vertex_ranges(view, place_runs(view, slot, reach, hops)) if reach > radius else inner
    best_in = best_out = math.inf
    for vid, dist in zip(hit_ids, hit_dists, strict=True):
        if any(a <= vid < b for a, b in inner):
            best_in = min(best_in, dist)
        elif dist < best_out and not any(a <= vid < b for a, b in outer) and (
                rivals is None or vid in rivals):  # (a rival's test only where it would count)
            best_out = dist
    if math.isinf(best_out):
        return 0.0
    if math.isinf(best_in):
        return math.inf
    return best_in / best_out if best_out > 0 else math.inf


def _vertex_ranges(view: BeliefView, runs: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """Slot runs of a place as global vertex id ranges (a run never crosses a sequence's
    end: :func:`place_runs`). O(runs log S)."""
    slot_first, seq_first = view.slot_first, view.graph.seq_first
    if len(slot_first) == 1:
        shift = int(seq_first[0]) - int(slot_first[0])
        return [(a + shift, b + shift) for a, b in runs]
    out = []
    for a, b in runs:
        s = int(np.searchsorted(slot_first, a, side="right")) - 1
        shift = int(seq_first[s]) - int(slot_first[s])
        out.append((a + shift, b + shift))
    return out


def _runs_sum(x: np.ndarray, runs: list[tuple[int, int]]) -> float:
    # A place is a handful of short runs: Python sums of small lists beat numpy reductions.
    if sum(b - a for a, b in runs) <= 64:
        return math.fsum(v for a, b in runs for v in x[a:b].tolist())
    if len(runs) == 1:
        start, stop = runs[0]
        return float(x[start:stop].sum())
    # Gather the slots of all runs and add them up: the runs may lie far apart in the
    # component, so no prefix sum over the span between them.
    starts = np.array([r[0] for r in runs], dtype=np.int64)
    lengths = np.array([r[1] - r[0] for r in runs], dtype=np.int64)
    slots = np.arange(int(lengths.sum()), dtype=np.int64) + np.repeat(
        starts - (np.cumsum(lengths) - lengths), lengths)
    return float(x[slots].sum())


def decide(views: list[BeliefView], candidates: list[tuple[float, int, int]], sink: float,
           radius: int, hops: int, min_confidence: float, n_active_components: int,
           n_active_vertices: int, prefer_seq: int | None = None,
           contrast_of: Callable[[BeliefView, int], float] | None = None) -> Decision:
    """Score candidates by place mass and apply the novelty rules.

    Parameters
    ----------
    views : list of BeliefView
    candidates : list of (vertex_prob, view index, slot)
        The most probable vertices, best first, all with positive belief.
    sink : float
        Sink posterior.
    radius, hops, min_confidence
        ``place_radius``, ``place_hops`` and ``min_confidence`` of the config.
    n_active_components, n_active_vertices : int
        Reported as is.
    prefer_seq : int, optional
        A sequence id to report the place by where the place holds it (that sequence's most
        probable vertex in the place); the place and its mass do not change.
    contrast_of : callable, optional
        ``contrast_of(view, slot)``: a match's ``contrast`` (NaN without it).

    Notes
    -----
    O(m (r + h d log d)) for m candidates (see :func:`place_runs`).
    """
    best: tuple[float, int, list[tuple[int, int]]] | None = None
    for _, vi, slot in candidates:
        runs = place_runs(views[vi], slot, radius, hops)
        mass = min(_runs_sum(views[vi].x, runs) * views[vi].scale, 1.0)
        if best is None or mass > best[0]:
            best = (mass, vi, runs)
    if best is None:
        return Decision(None, None, None, 0.0, 0.0, sink, n_active_components,
                        n_active_vertices, None)
    mass, vi, runs = best
    # Report the most probable candidate inside the winning place (candidates are sorted by
    # belief): its centre may be off the belief's peak by up to place_radius.
    prob, slot = next((p, sl) for p, v, sl in candidates
                      if v == vi and any(a <= sl < b for a, b in runs))
    view = views[vi]
    if prefer_seq is not None:
        slot, prob = _preferred(view, runs, prefer_seq, slot, prob)
    s = int(np.searchsorted(view.slot_first, slot, side="right")) - 1
    image = slot - int(view.slot_first[s])
    vid = int(view.graph.seq_first[s]) + image
    if is_unknown(mass, sink, min_confidence):
        return Decision(None, None, None, mass, prob, sink, n_active_components,
                        n_active_vertices, vid)
    contrast = math.nan if contrast_of is None else contrast_of(view, slot)
    return Decision(vid, int(view.graph.seq_ids[s]), image, mass, prob, sink,
                    n_active_components, n_active_vertices, vid, contrast)


def _preferred(view: BeliefView, runs: list[tuple[int, int]], seq_id: int, slot: int,
               prob: float) -> tuple[int, float]:
    """The most probable slot of sequence ``seq_id`` inside the place ``runs`` (with its
    posterior), or ``(slot, prob)`` unchanged if the place holds no belief on that sequence."""
    graph = view.graph
    s = 0 if len(graph.seq_ids) == 1 else int(np.searchsorted(graph.seq_ids, seq_id))
    if s >= len(graph.seq_ids) or int(graph.seq_ids[s]) != seq_id:
        return slot, prob
    lo = int(view.slot_first[s])
    hi = lo + int(graph.seq_len[s])
    best_slot, best = slot, -1.0
    for a, b in runs:
        a, b = max(a, lo), min(b, hi)
        if a < b:
            seg = view.x[a:b]
            i = int(seg.argmax())
            if seg[i] > best:
                best, best_slot = float(seg[i]), a + i
    if best <= 0.0:
        return slot, prob
    return best_slot, best * view.scale


def top_candidates(views: list[BeliefView], m: int) -> list[tuple[float, int, int]]:
    """The ``m`` most probable vertices over all views, best first.

    Only vertices holding at least :data:`CANDIDATE_FLOOR` times the largest belief qualify
    (such a vertex cannot seed the most massive place; the floor keeps ``argpartition`` away
    from the long runs of equal near-zero beliefs on which it degrades to O(n log n)-like work).

    Notes
    -----
    O(live slots of the views): a max, a comparison and a ``nonzero`` per view, then an
    ``argpartition`` over the qualifying vertices only.
    """
    lives = [v.live() for v in views]
    peak = max((float(vals.max()) * v.scale for v, (vals, _) in zip(views, lives, strict=True)
                if vals.size), default=0.0)
    if peak <= 0.0:
        return []
    floor = peak * CANDIDATE_FLOOR
    found: list[tuple[float, int, int]] = []
    for vi, (vals, slots) in enumerate(lives):
        scale = views[vi].scale
        pos = (vals >= floor / scale).nonzero()[0]
        if pos.size > m:
            sel = vals[pos]
            pos = pos[np.argpartition(sel, sel.size - m)[sel.size - m:]]
        probs = (vals[pos] * scale).tolist()
        where = (pos + slots).tolist() if isinstance(slots, int) else slots[pos].tolist()
        for slot, p in zip(where, probs, strict=True):
            found.append((p, vi, slot))
    found.sort(key=lambda c: (-c[0], c[1], c[2]))
    return found[:m]


#: :func:`top_positions` first ranks the values of at least this share of the largest.
_NEAR_PEAK = 0.01


def top_positions(values: np.ndarray, m: int) -> list[tuple[float, int]]:
    """The ``m`` largest of ``values`` (beliefs laid end to end) as ``(value, position)``,
    best first, equal values by position: :func:`top_candidates` of one view holding them
    all, so with the same :data:`CANDIDATE_FLOOR`.

    Notes
    -----
    O(n): a max, a comparison and a ``nonzero``, then a partition of the values of at least
    :data:`_NEAR_PEAK` times the largest (the ``m`` largest are among them when there are
    ``m`` of them; else of all qualifying values); every value equal to the ``m``-th largest
    is ranked, so ties never depend on the partition.
    """
    if not values.size or m <= 0:
        return []
    peak = float(values.max())
    if peak <= 0.0:
        return []
    pos = (values >= peak * _NEAR_PEAK).nonzero()[0]
    if pos.size < m:
        pos = (values >= peak * CANDIDATE_FLOOR).nonzero()[0]
    if pos.size > m:
        sel = values[pos]
        pos = pos[sel >= np.partition(sel, sel.size - m)[sel.size - m]]
    found = sorted(zip(values[pos].tolist(), pos.tolist(), strict=True),
                   key=lambda c: (-c[0], c[1]))
    return found[:m]
