"""Admission: which frames of a localised drive a map stores, and what it records instead.

A map created with ``admission="all"`` (the default) stores every frame of every drive. With
``admission="novel"`` it stores only what it does not already hold. A frame is **redundant**
when

1. the merge rule merged it (:mod:`sprint_map.merge.rule`): the map localised it confidently,
   on a run that stands out, and
2. the map already holds a view of that place that looks like the frame: the squared distance
   from the frame to the nearest of the decided vertex and its neighbours (``±2`` images) is at
   most ``max_step_ratio`` times the drive's own median squared distance between consecutive
   frames (how much the view changes from one frame to the next: a scale of "alike" that each
   drive brings, whatever the descriptor); or a view joined to those by an edge is a copy of
   the frame itself, closer than :data:`COPY_STEPS` of those steps (the drive ingested again,
   its place decided on an older drive's views).

A frame of which the map holds a copy (closer than :data:`COPY_STEPS` steps) is redundant even
if the rule did not merge it, matched or not: a view within one edge of its decided place, or
its best retrieval hit anywhere in the map. Storing it again adds nothing the map lacks (it
records no sighting: its place is not certified). Copies on both sides of a stretch shorter
than ``min_skip + 2 * margin`` frames make the stretch redundant too: the drive is a stored one
driven again, and the stretch is what that drive left out (a redundant stretch of at least
``min_skip`` frames, less the margins), which its run may now be too short to merge. So is a
stretch next to copies whose frames each have a view in the map (their best retrieval hit,
anywhere) as alike as their next frame (but for blips shorter than ``min_run``): at the ends
of such a drive, where no copy bounds what it left out.

Everything else is stored: unmapped stretches (nothing merged), stretches the map did not
localise confidently, and a known place seen under an appearance the map does not hold (merged
thanks to the sequence, but its views look unlike the frame). So a new condition is stored
until the map holds views of it; then it is redundant. Short flickers are smoothed away: a
stored stretch shorter than ``min_run`` frames is not stored, then a redundant stretch shorter
than ``min_skip`` frames between (or before or after) stored frames is stored. Each stored run
then takes ``margin`` redundant frames on either side: the run overlaps the places the drive
came from and went to, and its merged frames there keep their edges, so belief crosses into
the run and out of it over many edges, not one.

The stored frames become one sequence, in drive order (image ``j`` is the drive's ``j``-th
stored frame). What is not stored still counts:

- each redundant frame records a **sighting** of the vertex it was matched to
  (:mod:`sprint_map.storage.sightings`: how often, when and by which drive, at what distance);
- a stored frame that was merged keeps its merge edge(s), as with ``"all"``;
- each stored run is **stitched** into the map: an edge from the vertex the frame before the
  run was matched to into the run's first vertex (where the drive came from), and one from the
  run's last vertex to the vertex the frame after it was matched to (where it went), weighted
  by those decisions' probabilities. A later drive's belief flows along the map, into the new
  stretch and back out.

Runs of one drive are stored one after the other in its sequence, so the HMM's forward window
can carry belief from the end of one run into the start of the next (a few images): the
stitching edges carry the right belief, and the observations decide.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from sprint_map.merge.rule import MergeDecision
from sprint_map.storage.records import EdgeSpec
from sprint_map.util.dataclass_dict import check_int

__all__ = ["ADMISSION_MODES", "COPY_STEPS", "Admission", "AdmissionPlan", "drive_step",
           "place_distances", "plan_admission", "runs", "stored_mask", "stored_frames"]

#: ``all``: store every frame (the default); ``novel``: store what the map does not hold.
ADMISSION_MODES = ("all", "novel")

#: A view of the map closer to a frame than this many of its drive's (squared) steps is a stored
#: copy of the frame.
COPY_STEPS = 0.1


@dataclass(frozen=True)
class Admission:
    """Which frames a map stores (``MapConfig.admission``); see the module docstring.
    ValueError for a value out of range."""

    #: ``"all"`` (the default, recall parity) or ``"novel"`` (a smaller map for ~1 point of
    #: recall: ``docs/benchmarks.md``, "Bounded map").
    mode: str = "all"
    #: A merged frame this close to its place, in the drive's steps, is redundant (``novel``).
    max_step_ratio: float = 1.0
    #: Frames of the shortest stored run (``novel`` only).
    min_run: int = 5
    #: Frames of the shortest redundant stretch left out between stored frames (``novel``).
    min_skip: int = 20
    #: Redundant frames stored on either side of each stored run (``novel``).
    margin: int = 10

    def __post_init__(self) -> None:
        if self.mode not in ADMISSION_MODES:
            raise ValueError(f"admission must be one of {', '.join(ADMISSION_MODES)}, "
                             f"not {self.mode!r}")
        if not 0 <= self.max_step_ratio < math.inf:
            raise ValueError("admission max_step_ratio must be a finite number >= 0")
        check_int("admission min_run", self.min_run, 1)
        check_int("admission min_skip", self.min_skip, 1)
        check_int("admission margin", self.margin, 0)


@dataclass(frozen=True)
class AdmissionPlan:
    """What committing one localised drive stores (:func:`plan_admission`).

    ``stored``: bool per frame; ``image_of``: each frame's image id in the new sequence (-1
    where it is not stored); ``edges``: merge and stitching edges (``(None, image)`` is the new
    sequence); ``sightings``: ``(seq_id, image_id, distance)`` per redundant frame.
    """

    stored: np.ndarray
    image_of: np.ndarray
    edges: list[EdgeSpec] = field(default_factory=list)
    sightings: list[tuple[int, int, float]] = field(default_factory=list)

    @property
    def frames_stored(self) -> int:
        return int(self.stored.sum())

    def select(self, per_frame: Sequence[object] | np.ndarray | None) -> object:
        """``per_frame`` (rows, positions, thumbnails) reduced to the stored frames."""
        if per_frame is None:
            return None
        if isinstance(per_frame, np.ndarray):
            return per_frame[self.stored]
        return [x for x, keep in zip(per_frame, self.stored.tolist(), strict=True) if keep]


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[start, stop)`` of each run of True in ``mask``. O(n)."""
    padded = np.concatenate([[False], mask, [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(padded))
    return [(int(a), int(b)) for a, b in zip(edges[0::2], edges[1::2], strict=True)]


def stored_frames(decisions: Sequence[MergeDecision], merged: np.ndarray,
                  admission: Admission, closeness: np.ndarray | None,
                  nearest: np.ndarray | None = None) -> np.ndarray:
    """Which frames ``admission`` stores (bool per frame; see the module docstring):
    ``closeness`` is each frame's distance to its place in the drive's steps (NaN or inf where
    unknown: stored; at most :data:`COPY_STEPS`: a copy of the frame, redundant whether
    matched and merged or not; so is a stretch shorter than ``min_skip + 2 * margin`` frames
    between copies), ``nearest`` its distance to its best retrieval hit in those steps (a
    stretch of frames that many as alike as their next frame, next to a copy, is redundant,
    across blips shorter than ``min_run`` frames). O(n)."""
    n = len(decisions)
    if admission.mode == "all" or n == 0 or closeness is None:
        return np.ones(n, dtype=bool)
    matched = np.array([d.seq_id is not None for d in decisions], dtype=bool)
    with np.errstate(invalid="ignore"):
        alike = np.asarray(closeness, dtype=float) <= admission.max_step_ratio
        copy = np.asarray(closeness, dtype=float) <= COPY_STEPS
        near = (np.zeros(n, dtype=bool) if nearest is None
                else np.asarray(nearest, dtype=float) <= admission.max_step_ratio)
    redundant = (matched & np.asarray(merged, dtype=bool) & alike) | copy
    between = admission.min_skip + 2 * admission.margin
    for a, b in runs(~copy):
        if a > 0 and b < n and b - a < between:
            redundant[a:b] = True  # what a drive stored on both sides left out
    for a, b in runs(~near):
        if a > 0 and b < n and b - a < admission.min_run:
            near[a:b] = True  # a blip, as a stored run shorter than min_run would be
    for a, b in runs(near & ~copy):
        if (a > 0 and copy[a - 1]) or (b < n and copy[b]):
            redundant[a:b] = True  # what a stored drive driven again left out, at its ends
    return stored_mask(redundant, admission)


def stored_mask(redundant: np.ndarray, admission: Admission) -> np.ndarray:
    """Which frames of a drive (or a stored sequence) are kept, from which are redundant:
    stored runs shorter than ``min_run`` dropped, redundant stretches shorter than
    ``min_skip`` stored through, ``margin`` frames added either side of each stored run (see
    the module docstring). O(n)."""
    n = len(redundant)
    stored: np.ndarray = ~np.asarray(redundant, dtype=bool)
    for a, b in runs(stored):
        if b - a < admission.min_run and b - a < n:
            stored[a:b] = False
    for a, b in runs(~stored):
        if b - a < admission.min_skip and b - a < n:
            stored[a:b] = True
    if admission.margin and not stored.all():
        for a, b in runs(stored):
            stored[max(0, a - admission.margin):b + admission.margin] = True
    return stored


def plan_admission(decisions: Sequence[MergeDecision], merged: np.ndarray,
                   admission: Admission, both_ways: bool,
                   place_dist: np.ndarray | None = None, step: float = math.inf,
                   nearest_dist: np.ndarray | None = None) -> AdmissionPlan:
    """What to store of a drive, its edges and its sightings (see the module docstring).

    ``decisions`` are the drive's consecutive frames (``frame`` is ``0 .. n-1``), ``merged``
    the merge rule's verdict per decision, ``place_dist`` each frame's squared distance to its
    place and ``step`` the drive's median squared distance between consecutive frames
    (:func:`place_distances`; None, or an infinite step: every frame is stored). With
    ``admission.mode == "all"`` every frame is stored and the edges are the merge edges
    (:func:`sprint_map.merge.commit.merge_edges`).

    Notes
    -----
    O(n) for n decisions.
    """
    n = len(decisions)
    merged = np.asarray(merged, dtype=bool) if len(merged) else np.zeros(n, dtype=bool)
    # Without a finite step (a one-frame drive) there is no scale of "alike": store all.
    closeness = (None if place_dist is None or not math.isfinite(step)
                 else place_dist / max(step, 1e-30))
    near = (None if closeness is None or nearest_dist is None
            else np.asarray(nearest_dist, dtype=float) / max(step, 1e-30))
    stored = stored_frames(decisions, merged, admission, closeness, near)
    image_of = np.full(n, -1, dtype=np.int64)
    image_of[stored] = np.arange(int(stored.sum()), dtype=np.int64)
    edges: list[EdgeSpec] = []
    sightings: list[tuple[int, int, float]] = []
    for i, d in enumerate(decisions):
        if not merged[i] or d.seq_id is None or d.image_id is None:
            continue
        if not stored[i]:
            assert place_dist is not None
            sightings.append((d.seq_id, d.image_id, float(place_dist[i])))
            continue
        j = int(image_of[i])
        weight = min(1.0, float(d.prob))
        edges.append(EdgeSpec((None, j), (d.seq_id, d.image_id), weight, j))
        if both_ways:
            edges.append(EdgeSpec((d.seq_id, d.image_id), (None, j), weight, j))
    if admission.mode != "all":
        edges.extend(_stitches(decisions, merged, stored, image_of))
    return AdmissionPlan(stored, image_of, edges, sightings)


def drive_step(rows: np.ndarray) -> float:
    """The drive's median squared distance between consecutive frames (inf for one frame).
    O(n * dim)."""
    if len(rows) < 2:
        return math.inf
    diff = np.diff(np.asarray(rows, dtype=np.float32), axis=0)
    return float(np.median(np.einsum("ij,ij->i", diff, diff)))


def place_distances(rows: np.ndarray, decisions: Sequence[MergeDecision], merged: np.ndarray,
                    read: Callable[[int, int, int], np.ndarray], lengths: Callable[[int], int],
                    radius: int = 2,
                    linked: Callable[[int, int, int], Sequence[tuple[int, int]]] | None = None,
                    copy_limit: float = 0.0, copies: np.ndarray | None = None) -> np.ndarray:
    """Each merged frame's squared distance to the nearest view of its place: the decided
    image and up to ``radius`` images either side on its sequence, or, closer than
    ``copy_limit``, a copy of the frame: among the images around those that ``linked`` joins
    to them by an edge, or anywhere in the map, its best retrieval hit at distance
    ``copies[i]`` (inf where unknown); for any other frame, the distance to such a copy only
    (inf for the other frames). ``read(seq_id, start, stop)`` gives stored rows,
    ``lengths(seq_id)`` a sequence's length (0 for one no longer in the map), ``linked(seq_id,
    start, stop)`` the ``(seq_id, image_id)`` joined by an edge to images ``start .. stop - 1``.

    Notes
    -----
    O(m * (1 + e) * (2 radius + 1) * dim) for m merged (with ``copy_limit``: matched) frames
    with e linked images each, plus the reads.
    """
    out = np.full(len(decisions), np.inf)
    hit = (np.full(len(decisions), np.inf) if copies is None
           else np.where(np.asarray(copies, dtype=float) <= copy_limit, copies, np.inf))

    def nearest(i: int, seq_id: int, image_id: int) -> float:
        lo, hi = max(0, image_id - radius), min(lengths(seq_id), image_id + radius + 1)
        if hi <= lo:  # a sequence removed since the drive was localised
            return math.inf
        views = np.asarray(read(seq_id, lo, hi), dtype=np.float32) - rows[i]
        return float(np.einsum("ij,ij->i", views, views).min())

    for i, d in enumerate(decisions):
        out[i] = hit[i]
        if d.seq_id is None or d.image_id is None or not (merged[i] or copy_limit > 0):
            continue
        if not merged[i] and hit[i] < math.inf:
            continue  # a copy already
        near = nearest(i, d.seq_id, d.image_id)
        if linked is not None and copy_limit < min(near, hit[i]) and near < math.inf:
            for seq_id, image_id in linked(d.seq_id, max(0, d.image_id - radius),
                                           d.image_id + radius + 1):
                if (view := nearest(i, seq_id, image_id)) <= copy_limit:
                    near = view
                    break
        if merged[i] or near <= copy_limit:
            out[i] = min(near, hit[i])
    return out


def _stitches(decisions: Sequence[MergeDecision], merged: np.ndarray, stored: np.ndarray,
              image_of: np.ndarray) -> list[EdgeSpec]:
    """The edges into and out of each stored run from the places the drive was matched to
    right before and after it (only where those frames were merged and not stored)."""
    out: list[EdgeSpec] = []
    n = len(decisions)
    for a, b in runs(stored):
        if a > 0 and merged[a - 1] and not stored[a - 1]:
            before = decisions[a - 1]
            if before.seq_id is not None and before.image_id is not None:
                first = int(image_of[a])
                out.append(EdgeSpec((before.seq_id, before.image_id), (None, first),
                                    min(1.0, float(before.prob)), first))
        if b < n and merged[b] and not stored[b]:
            after = decisions[b]
            if after.seq_id is not None and after.image_id is not None:
                last = int(image_of[b - 1])
                out.append(EdgeSpec((None, last), (after.seq_id, after.image_id),
                                    min(1.0, float(after.prob)), last))
    return out
