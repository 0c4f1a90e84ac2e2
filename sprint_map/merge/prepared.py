"""A drive localised against a snapshot now, committed later: what an ingest farm needs.

``SprintMap.ingest`` localises a drive against the map as it stands and commits it at once. A
farm (:mod:`sprint_map.fleet.farm`) localises many drives in parallel, each against a read-only
snapshot, and one writer commits them in order. Its result must equal serial ingest in the same
order, so at commit time the writer asks whether the drives committed since the snapshot could
have changed this drive's localisation (:func:`stale_reason`); if so the drive is localised
again against the map as it now is (``SprintMap.ingest``), else its decisions are committed as
they are.

A drive's localisation reads only (a) its frames' k-NN hits and (b) the components those hits
fall in (their sequences and edges). With one writer appending drives, (a) changes only if a
vertex committed since the snapshot comes within a frame's k-th hit distance, and (b) only if a
drive committed since merged into one of those components, which then has more sequences. Both
are checked exactly (a near-tie counts as a change); an index other than the exact flat one
(the segmented index re-ranks a candidate set that any new vertex can alter) and any removal
make every commit since the snapshot a change.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from sprint_map.hmm.config import HMMConfig
from sprint_map.localize.localizer import (
    FrameDecision,
    LocalizableMap,
    Localizer,
    LocalizerConfig,
    Timing,
)
from sprint_map.merge.smoothing import MergeSettings, smoothed_decisions
from sprint_map.storage.store import MapStore
from sprint_map.util.arrays import Descriptors, DescriptorsLike
from sprint_map.util.lazy import faiss  # imported on first use

__all__ = ["PreparableConfig", "PreparableMap", "PreparedDrive", "prepare_drive", "stale_reason"]

#: Relative margin under which a new vertex's distance counts as reaching a frame's k-th hit.
TIE_MARGIN = 1e-4


@dataclass(frozen=True)
class PreparedDrive:
    """One drive's localisation against a snapshot, ready to commit (picklable).

    Attributes
    ----------
    localised : bool
        False when the drive is appended as it is (``merge`` off, or an empty map).
    snapshot_vertices : int
        ``next_vertex_id`` of the snapshot: ids at or above it were committed after.
    kth_distance : ndarray (N,)
        Each frame's k-th hit distance (inf with fewer than k hits).
    touched : dict
        Component (root sequence id) -> its sequence ids, for every component a hit fell in.
    index : str
        The index as the snapshot's reader saw it (its type and sealed count).
    removed : int
        Removed vertices as of the snapshot.
    centring : DriveCentring or None
        A fresh copy of the centring the drive was localised with (its prior): its commit
        stores the rows centred as they were searched.
    """

    localised: bool
    merge: bool
    snapshot_vertices: int
    decisions: list[FrameDecision] = field(default_factory=list)
    timing: Timing = field(default_factory=Timing)
    kth_distance: np.ndarray = field(default_factory=lambda: np.zeros(0))
    touched: dict[int, frozenset[int]] = field(default_factory=dict)
    index: str = ""
    removed: int = 0
    centring: Any = None


class PreparableConfig(LocalizerConfig, MergeSettings, Protocol):
    """What preparing a drive reads of a map's config: the localizer's and the merge's."""


class PreparableMap(LocalizableMap, Protocol):
    """What preparing and checking a drive read of a map (:class:`sprint_map.map.SprintMap`
    is one): its counts, the rows committed since a snapshot, its thumbnails, and its store's
    removed vertices, index and components."""

    @property
    def config(self) -> PreparableConfig: ...

    def thumbnail(self, seq_id: int, image_id: int) -> bytes | None: ...

    @property
    def store(self) -> MapStore: ...

    def stats(self) -> dict[str, int]: ...

    def vertex_rows(self, start: int, stop: int | None = None) -> Descriptors: ...


def index_state(smap: PreparableMap) -> str:
    """The index's kind and sealed extent: equal strings, equal search over the old vertices
    (exact flat: always; segmented: only if nothing was sealed or retrained)."""
    described = smap.store.index.describe()
    return f"{described.get('type', '')}/{described.get('sealed', '')}"


def prepare_drive(smap: PreparableMap, batches: Iterable[DescriptorsLike], *, merge: bool = True,
                  hmm: HMMConfig | None = None) -> PreparedDrive:
    """Localise a drive (its search batches, as ``ingest`` would get them) against one
    snapshot of ``smap`` (read-only is enough), as ``SprintMap.ingest`` would.

    Notes
    -----
    The cost of ``ingest``'s localisation, plus one component load per component the hits
    touched.
    """
    if not merge:
        return PreparedDrive(False, False, smap.stats()["vertices"])
    localizer = Localizer(smap, hmm, record=True)
    with localizer.source.pinned():
        vertices = localizer.source.vertices
        # Read beside the pin: only a writer removes, and the farm's writer is the only one.
        removed = smap.store.removed_vertices()
        if not vertices:
            return PreparedDrive(False, True, 0, removed=removed)
        for batch in batches:
            for _ in localizer.iter_localize(iter([batch])):
                pass
        decisions = smoothed_decisions(localizer, smap)
        k = localizer.search_k
        kth = np.array([float(d[ids >= 0].max()) if int((ids >= 0).sum()) >= k else math.inf
                        for ids, d in localizer.hits])
        hit_ids = np.unique(np.concatenate([ids[ids >= 0] for ids, _ in localizer.hits]
                                           or [np.zeros(0, np.int64)]))
        touched = {int(root): frozenset(int(s) for s in
                                        localizer.source.load_component(int(root)).seq_ids)
                   for root in np.unique(localizer.source.components_of(hit_ids))}
        state = index_state(smap)
    return PreparedDrive(True, True, vertices, decisions, localizer.timing, kth, touched,
                         state, removed, localizer.centring.fresh())


def stale_reason(smap: PreparableMap, drive: PreparedDrive, rows: DescriptorsLike) -> str | None:
    """Why ``drive`` (whose descriptors are ``rows``) must be localised again before its
    commit to ``smap`` as it now is, or None if its decisions are those serial ingest would
    make now.

    Notes
    -----
    O(N * M * dim) for the M vertices committed since the snapshot (one exact 1-NN of the
    drive's frames among them) plus O(components touched) reads.
    """
    vertices = smap.stats()["vertices"]
    if not drive.merge:
        return None
    if not drive.localised:
        return "the map was empty at the snapshot" if vertices else None
    if vertices == drive.snapshot_vertices:
        return None
    if smap.store.removed_vertices() != drive.removed:
        return "sequences were removed since the snapshot"
    if index_state(smap) != drive.index or not drive.index.startswith("IndexIDMap2"):
        return "the index is not the exact flat one, or changed, since the snapshot"
    new = np.ascontiguousarray(smap.vertex_rows(drive.snapshot_vertices, vertices),
                               dtype=np.float32)
    nearest = faiss.knn(np.ascontiguousarray(rows, dtype=np.float32), new, 1)[0][:, 0]
    reach = drive.kth_distance * (1 + TIE_MARGIN) + 1e-6
    if (nearest.astype(np.float64) <= reach).any():
        return "a vertex committed since the snapshot is among a frame's k nearest"
    for root, members in drive.touched.items():
        now = smap.store.component_of(root)
        if now != root or {s.seq_id for s in component_sequences(smap, now)} != members:
            return f"component {root} changed since the snapshot"
    return None


def component_sequences(smap: PreparableMap, root: int) -> list[Any]:
    """The sequences of component ``root`` as of now."""
    with smap.store.env.read() as txn:
        return smap.store.component_sequences(root, txn)
