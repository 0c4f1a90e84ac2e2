"""Joining maps: drives of another map copied in, then localised and merged as ``ingest`` would.

A fleet's vehicles map apart; at the end of the day their maps come together
(``sprint-map join TARGET SOURCE``, :meth:`SprintMap.join <sprint_map.map.SprintMap.join>`):

1. **Compatibility** (:func:`check_compatible`): the same descriptor kind, dimension and
   parameters (an ONNX model's digest is one of them) and the same coordinate frame, else one
   :class:`~sprint_map.errors.IncompatibleMapError` naming the difference.
2. **Plan** (:func:`sprint_map.storage.join.plan_join`): which drives (``drives``, by name), the
   names they take (``prefix``; a clash is refused with every clashing name), which ones the
   target already holds (same content digest: not copied again, so joining twice is a no-op).
3. **Localise** each imported drive against what the target held before the join, exactly as
   ``ingest`` would (:func:`localise_drive`: the same localizer with the drive's GNSS fixes,
   the same after-drive smoothing and verification on its thumbnails, the same merge rule and
   edges, :func:`sprint_map.merge.commit.merge_edges`). Drives are independent here (each sees
   the same target), so a farm may localise them in parallel with the same result.
4. **Connectivity**: an imported drive is connected to what the target held if its own
   cross-map edges, or the copied edges among the imported drives, or an edge to a drive the
   target already held, lead there. ``require_connected`` refuses (nothing written) a join
   that leaves one unconnected (:class:`~sprint_map.errors.UnconnectedJoinError`).
5. **Commit** (:func:`sprint_map.storage.join.copy_drives`): one transaction of the target.

The cross-map edges are the imported drive's (``added_by`` it, ``frame`` its frame), like an
ingest's: ``edges --added-by DRIVE`` lists them and ``unmerge TARGET DRIVE`` revokes them (with
the drive's own merges it brought along, which it also added).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from sprint_map.errors import IncompatibleMapError, UnconnectedJoinError
from sprint_map.hmm.config import HMMConfig
from sprint_map.localize.localizer import LocalizerService
from sprint_map.merge.commit import merge_edges
from sprint_map.merge.prepared import PreparableMap
from sprint_map.merge.rule import select_merges
from sprint_map.storage.join import JoinPlan, copy_drives, drive_rows, plan_join
from sprint_map.storage.records import EdgeSpec, SequenceRecord
from sprint_map.storage.store import MapStore
from sprint_map.testing.crash import crash_point
from sprint_map.util.union_find import UnionFind

if TYPE_CHECKING:  # a copy (``merge=False``) loads no HMM
    from sprint_map.localize.gnss import GnssAid

__all__ = ["DriveLocalisation", "JoinResult", "JoinedDrive", "JoiningMap", "JoiningService",
           "LocaliseMany", "check_compatible",
           "connected_drives", "join_maps", "localise_drive"]


class JoiningService(LocalizerService, Protocol):
    """What a join uses of the target's service API (:class:`sprint_map.facade.service.MapService`
    is one): what a localizer is made of, and the GNSS aid of a drive's fixes."""

    def gnss_aid(self, fixes: np.ndarray | None, frames: int | None, *, index: bool = True
                 ) -> GnssAid | None: ...


class JoiningMap(PreparableMap, Protocol):
    """What a join uses of the target (:class:`sprint_map.map.SprintMap` is one): what
    localising a drive reads, and its service API."""

    @property
    def service(self) -> JoiningService: ...


#: What a farm's worker does for one drive: localise source drive ``seq_id`` (its record
#: given) against the target as it is before the join.
LocaliseMany = Callable[[Sequence[SequenceRecord]], list["DriveLocalisation"]]


@dataclass(frozen=True)
class DriveLocalisation:
    """One imported drive localised against the target (picklable): its cross-map edges and
    how many of its frames matched / were merged."""

    seq_id: int
    edges: list[EdgeSpec]
    frames: int
    matched: int
    merged: int
    #: the localisation's time in the search and in the HMM (per-frame lists summed), and in
    #: the after-drive smoothing, milliseconds
    retrieval_ms: float = 0.0
    hmm_ms: float = 0.0
    smooth_ms: float = 0.0


@dataclass(frozen=True)
class JoinedDrive:
    """What the join did with one source drive."""

    source_seq_id: int
    source_name: str
    seq_id: int
    name: str
    frames: int
    #: the target held its rows already (same content digest): nothing copied
    already_present: bool
    #: edges its merge added to what the target held
    cross_edges: int
    matched: int
    #: whether it now has a path to a drive the target held before the join
    connected: bool
    component: int

    def to_dict(self) -> dict[str, Any]:
        return {"source_seq_id": self.source_seq_id, "source_name": self.source_name,
                "seq_id": self.seq_id, "name": self.name, "frames": self.frames,
                "already_present": self.already_present, "cross_edges": self.cross_edges,
                "matched": self.matched, "connected": self.connected,
                "component": self.component}


@dataclass(frozen=True)
class JoinResult:
    """What :func:`join_maps` did: per source drive, and the totals."""

    drives: list[JoinedDrive]
    vertices_copied: int
    edges_copied: int
    edges_dropped: int
    cross_edges: int
    merged: bool
    copy_seconds: float
    localise_seconds: float
    #: the localisations' search, HMM and smoothing time, milliseconds in all
    retrieval_ms: float = 0.0
    hmm_ms: float = 0.0
    smooth_ms: float = 0.0

    @property
    def frames_localised(self) -> int:
        return sum(d.frames for d in self.drives if not d.already_present) if self.merged else 0

    def to_dict(self) -> dict[str, Any]:
        frames = self.frames_localised
        return {
            "drives": [d.to_dict() for d in self.drives],
            "imported": sum(not d.already_present for d in self.drives),
            "already_present": sum(d.already_present for d in self.drives),
            "vertices_copied": self.vertices_copied,
            "edges_copied": self.edges_copied,
            "edges_dropped": self.edges_dropped,
            "cross_edges": self.cross_edges,
            "merged": self.merged,
            "copy_seconds": round(self.copy_seconds, 4),
            "localise_seconds": round(self.localise_seconds, 4),
            "localise_ms_per_frame": round(1e3 * self.localise_seconds / frames, 4)
            if frames else None,
            "retrieval_ms": round(self.retrieval_ms, 3),
            "hmm_ms": round(self.hmm_ms, 3),
            "smooth_ms": round(self.smooth_ms, 3),
        }


#: The config fields that must agree (a dotted path into the config's dict form).
COMPATIBLE_FIELDS = ("descriptor", "dim", "descriptor_params")


def check_compatible(target: dict[str, Any], source: dict[str, Any],
                     target_frame: dict[str, Any] | None, source_frame: dict[str, Any] | None,
                     target_placed: bool, source_placed: bool) -> None:
    """Refuse to join maps whose descriptors or coordinate frames differ.

    ``target``/``source``: the maps' configs (``MapConfig.to_dict()``); ``*_frame``: their
    geographic frames (None: none recorded); ``*_placed``: whether they store any position.
    Two maps placed in different frames (two UTM zones, or one geographic and one local) cannot
    be joined; a map without positions takes the other's frame. O(fields).

    Raises
    ------
    IncompatibleMapError
        Naming the first difference (field, and both values).
    """
    for name in COMPATIBLE_FIELDS:
        a, b = target.get(name), source.get(name)
        if name == "descriptor_params" and isinstance(a, dict) and isinstance(b, dict):
            for key in sorted(set(a) | set(b)):
                if a.get(key) != b.get(key):
                    raise IncompatibleMapError(
                        f"the maps' descriptors differ: {name}.{key} is {a.get(key)!r} in the "
                        f"target and {b.get(key)!r} in the source")
        elif a != b:
            raise IncompatibleMapError(f"the maps' descriptors differ: {name} is {a!r} in the "
                                       f"target and {b!r} in the source")
    # the space the rows are stored in (a config stored before centring: as described)
    spaces = [(c.get("centring") or {"mode": "none"}).get("mode") for c in (target, source)]
    if spaces[0] != spaces[1]:
        raise IncompatibleMapError(f"the maps store their rows in different spaces: centring "
                                   f"is {spaces[0]!r} in the target and {spaces[1]!r} in the "
                                   "source")
    if target_placed and source_placed and target_frame != source_frame:
        def describe(frame: dict[str, Any] | None) -> str:
            return ("local metric (no geographic frame)" if frame is None
                    else f"UTM zone {frame.get('zone')}{'S' if frame.get('south') else 'N'}")
        raise IncompatibleMapError(
            f"the maps' positions are in different coordinate frames: "
            f"{describe(target_frame)} in the target, {describe(source_frame)} in the source")


def localise_drive(smap: JoiningMap, source: MapStore, record: SequenceRecord,
                   hmm: HMMConfig | None = None) -> DriveLocalisation:
    """Localise source drive ``record`` against ``smap`` as it is, as ``ingest`` would, and
    return the edges its merge would add (src ``None``: the drive itself).

    The drive's stored positions are its GNSS fixes (``x, y, sigma_m``), as ``ingest`` takes a
    drive's positions; its thumbnails (if it has them) turn verification on.

    Notes
    -----
    ``ingest``'s cost per frame (one batched k-NN search, one HMM step, the smoothing passes),
    plus reading the drive's rows, positions and thumbnails from the source.
    """
    from sprint_map.localize.localizer import SEARCH_BATCH, Localizer
    from sprint_map.merge.smoothing import smoothed_decisions

    with source.env.read() as txn:
        total = source.counter("next_vertex_id", txn)
    positions = source.positions(record.seq_id)
    fixes = None
    if positions is not None:
        wide = np.full((len(positions), 5), np.nan)
        wide[:, : positions.shape[1]] = positions
        fixes = wide[:, [0, 1, 4]]
    thumbs = [source.thumbnail(record.seq_id, i) for i in range(record.length)] \
        if source.thumbnail_count(record.seq_id) else None
    # the source's rows are centred already: searched as they are
    localizer = Localizer(smap, hmm, record=True, gnss=smap.service.gnss_aid(fixes, record.length),
                          in_map_space=True)
    for batch in drive_rows(source, record, total, SEARCH_BATCH):
        for _ in localizer.iter_localize(iter([np.asarray(batch)])):
            pass
    thumbnails = None if thumbs is None or any(t is None for t in thumbs) else \
        [t for t in thumbs if t is not None]
    decisions = smoothed_decisions(localizer, smap, None, thumbnails)
    merged = select_merges(decisions, smap.config.merge)
    edges = merge_edges(decisions, merged, smap.config.merge.both_ways)
    return DriveLocalisation(record.seq_id, edges, record.length,
                             sum(d.seq_id is not None for d in decisions), int(merged.sum()),
                             float(sum(localizer.timing.retrieval_ms)),
                             float(sum(localizer.timing.hmm_ms)), localizer.timing.smooth_ms)


def connected_drives(plan: JoinPlan, crossing: set[int]) -> dict[int, bool]:
    """Per imported drive (source seq_id): whether it reaches a drive the target held before
    the join, through ``crossing`` (the imported drives with a cross-map edge), the carried
    edges among imported drives and those to a drive the target held. O(n + links)."""
    index = {d.source.seq_id: i for i, d in enumerate(plan.drives)}
    sets = UnionFind(len(plan.drives))
    for a, b in plan.links:
        sets.union(index[a], index[b])
    seeds = {sets.find(index[d.source.seq_id]) for d in plan.drives
             if d.present_as is not None or d.source.seq_id in crossing}
    return {d.source.seq_id: sets.find(index[d.source.seq_id]) in seeds for d in plan.imports}


def join_maps(smap: JoiningMap, source: MapStore, configs: tuple[dict[str, Any], dict[str, Any]],
              *, drives: Sequence[str] | None = None,
              prefix: str = "", merge: bool = True, require_connected: bool = False,
              hmm: HMMConfig | None = None, localise_many: LocaliseMany | None = None,
              progress: Callable[[int], None] | None = None,
              exclusive: Callable[[], AbstractContextManager[Any]] | None = None,
              on_commit: Callable[[set[int]], None] | None = None) -> JoinResult:
    """Join drives of ``source`` (open read-only) into ``smap`` (open for writing): see the
    module docstring. ``configs``: the target's and the source's configs (``to_dict()``). ``localise_many`` localises several drives (a farm; default: one after
    the other here); ``progress`` gets the rows localised or copied since its last call
    (each imported row twice with ``merge``); ``exclusive`` and ``on_commit``: the service's
    gate and component registry around the commit
    (:func:`~sprint_map.storage.join.copy_drives`).

    Raises
    ------
    IncompatibleMapError, UnknownSequenceError, DuplicateNameError, UnconnectedJoinError
        Before anything is written (see the module docstring).
    StorageIOError
        The target cannot be written; nothing is committed.

    Notes
    -----
    ``ingest``'s localisation cost for every imported frame (none with ``merge`` off or an
    empty target), then the copy: O(N * dim) row I/O and O(N + E) LMDB puts in one
    transaction.
    """
    store = smap.store
    target_frame, source_frame = store.geo_frame(), source.geo_frame()
    check_compatible(*configs, target_frame, source_frame,
                     _placed(store), _placed(source))
    plan = plan_join(store, source, drives, prefix)
    started = time.monotonic()
    localise = merge and smap.stats()["vertices"] > 0
    found: dict[int, DriveLocalisation] = {}
    if localise and plan.imports:
        records = [d.source for d in plan.imports]
        if localise_many is not None:
            results = localise_many(records)
        else:
            results = []
            for rec in records:
                results.append(localise_drive(smap, source, rec, hmm))
                if progress is not None:
                    progress(rec.length)
        found = {r.seq_id: r for r in results}
    localised = time.monotonic() - started
    crash_point("join.localised")
    crossing = {seq for seq, r in found.items() if r.edges}
    connected = connected_drives(plan, crossing)
    if require_connected:
        alone = [d.name for d in plan.imports if not connected[d.source.seq_id]]
        if alone:
            raise UnconnectedJoinError(
                f"the join would leave {len(alone)} imported drive(s) unconnected to what the "
                f"target held: {', '.join(map(repr, alone[:10]))}"
                f"{', ...' if len(alone) > 10 else ''}; nothing was changed")
    began = time.monotonic()
    copied = copy_drives(store, source, plan, {s: r.edges for s, r in found.items()},
                         progress, exclusive=exclusive, on_commit=on_commit) \
        if plan.imports else []
    crash_point("join.committed")
    copy_seconds = time.monotonic() - began
    by_source = {c.source.seq_id: c.added for c in copied}
    out = []
    for d in plan.drives:
        sid = d.source.seq_id
        added = by_source.get(sid)
        held = added.sequence if added is not None else d.present_as
        assert held is not None  # a drive not copied is one the target holds
        loc = found.get(sid)
        out.append(JoinedDrive(
            sid, d.source.name, held.seq_id, held.name, d.source.length, d.present_as is not None,
            added.edges_added if added is not None else 0, loc.matched if loc else 0,
            connected.get(sid, True), store.component_of(held.seq_id)))
    return JoinResult(out, sum(d.length for d in (c.source for c in copied)), plan.edges,
                      plan.edges_dropped, sum(d.cross_edges for d in out), localise,
                      copy_seconds, localised, sum(r.retrieval_ms for r in found.values()),
                      sum(r.hmm_ms for r in found.values()),
                      sum(r.smooth_ms for r in found.values()))


def _placed(store: MapStore) -> bool:
    """Whether the map stores any position. O(1): one cursor seek."""
    with store.env.read() as txn:
        return bool(txn.cursor(db=store.env.db("vertex_data")).first())
