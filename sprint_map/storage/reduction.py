"""A map's summary written as a new generation: which vertices go, what stands for them.

``sprint-map summarize`` (:mod:`sprint_map.merge.summary` decides what is redundant) removes
vertices from the middle of sequences. Sequences have no holes (a vertex is a row, a sequence a
range of rows), so a summary is written the way ``compact`` writes a map
(:func:`sprint_map.storage.compaction.compact_map`): a complete new generation, selected
atomically, in which every kept vertex is renumbered densely and the image ids of a summarised
sequence are its kept frames in order. A :class:`Reduction` says, per vertex id:

- ``keep``: whether the vertex stays; a sequence that keeps none of its frames goes whole;
- ``redirect``: for a dropped vertex, the kept vertex (of an older sequence) that stands for
  it. Every edge to or from a dropped vertex is moved onto its stand-in (dropped if it has none,
  or if the moved edge would join a sequence to itself; a repeated edge keeps the newest
  provenance); the dropped vertex's sighting record, if any, is folded into the stand-in's;
- ``stitches``: new edges (old vertex ids) that carry belief from the place a dropped stretch
  began into the kept frame after it, and from the last kept frame into the place it went;
- ``sightings``: one sighting of a stand-in per dropped vertex, as admission records one for
  a frame it does not store (:mod:`sprint_map.storage.sightings`).

Sequence ids, names and the order of sequences (commit order) are kept, so provenance,
``unmerge`` and ``remove`` work on the summary as before. A summarised sequence's digest is
recomputed over its kept rows. Components are regrouped from the edges that remain.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import lmdb
import numpy as np

from sprint_map.errors import InputError
from sprint_map.storage.keys import EDGE_KEY, EDGE_VAL, SEQ_IMAGE_KEY
from sprint_map.storage.lmdb_env import LmdbEnv
from sprint_map.storage.records import EdgeRecord, SequenceRecord
from sprint_map.storage.removal import write_component
from sprint_map.storage.sightings import SIGHTINGS_DB, decode_sighting, encode_sighting
from sprint_map.util.union_find import UnionFind

__all__ = ["Reduction", "reduced_edges", "reduced_sightings", "reduced_thumbnails",
           "regroup_all"]

#: ``(old ids) -> (new ids, live mask)``: a compaction's renumbering.
Renumber = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


@dataclass(frozen=True)
class Reduction:
    """What a summary drops and what stands for it (see the module docstring); vertex ids are
    the map's current ones, ``0 .. total-1``."""

    #: bool per vertex id: it stays
    keep: np.ndarray
    #: int64 per vertex id: the kept vertex standing for a dropped one, -1 for none
    redirect: np.ndarray
    #: new edges between kept vertices (old ids; provenance as given)
    stitches: list[EdgeRecord] = field(default_factory=list)
    #: ``(stand-in vertex, squared distance, drive name, when)``: one sighting each
    sightings: list[tuple[int, float, str, float]] = field(default_factory=list)

    def validate(self, total: int) -> None:
        """InputError unless the arrays cover ``total`` vertices and every stand-in, stitch
        end and sighting names a kept vertex. O(total)."""
        if self.keep.shape != (total,) or self.redirect.shape != (total,):
            raise InputError(f"a reduction must cover the map's {total} vertex ids")
        targets = self.redirect[self.redirect >= 0]
        if len(targets) and (targets.max() >= total or not self.keep[targets].all()):
            raise InputError("a dropped vertex is redirected to a vertex that is not kept")
        ends = [e for s in self.stitches for e in (s.src, s.dst)]
        ends += [v for v, *_ in self.sightings]
        if ends and not (max(ends) < total and self.keep[np.asarray(ends)].all()):
            raise InputError("a stitch or a sighting names a vertex that is not kept")

    @property
    def dropped(self) -> int:
        return int((~self.keep).sum())


def _moved(ids: np.ndarray, reduction: Reduction) -> np.ndarray:
    """Each id, or its stand-in where it is dropped (-1: none)."""
    return np.where(reduction.keep[ids], ids, reduction.redirect[ids])


def reduced_edges(txn: lmdb.Transaction, env: LmdbEnv, renumber: Renumber,
                  seq_starts: np.ndarray, reduction: Reduction) -> list[tuple[bytes, bytes]]:
    """Every edge of ``env`` and the stitches, moved off dropped vertices and renumbered:
    ``(key, value)`` sorted by key. ``seq_starts``: the new first vertex of each new sequence,
    ascending (to drop an edge a move turned into one within a sequence).

    Notes
    -----
    O(E log E) for E edges, in memory.
    """
    keys: list[bytes] = []
    values: list[bytes] = []
    for key, value in txn.cursor(db=env.db("edges")):
        keys.append(bytes(key))
        values.append(bytes(value))
    for stitch in reduction.stitches:
        keys.append(EDGE_KEY.pack(stitch.src, stitch.dst))
        values.append(stitch.encode_value())
    if not keys:
        return []
    ids = np.frombuffer(b"".join(keys), dtype=">u8").astype(np.int64).reshape(-1, 2)
    moved = _moved(ids, reduction)
    usable = (moved >= 0).all(axis=1)
    new_ids, live = renumber(np.where(moved >= 0, moved, 0))
    usable &= live.all(axis=1)
    seq = np.searchsorted(seq_starts, new_ids, side="right")
    usable &= seq[:, 0] != seq[:, 1]
    best: dict[bytes, bytes] = {}
    for i in np.flatnonzero(usable).tolist():
        key = EDGE_KEY.pack(int(new_ids[i, 0]), int(new_ids[i, 1]))
        held = best.get(key)
        # a repeated edge keeps its newest provenance (as a commit writing it again would)
        if held is None or EDGE_VAL.unpack(values[i])[3] >= EDGE_VAL.unpack(held)[3]:
            best[key] = values[i]
    return sorted(best.items())


def reduced_thumbnails(txn: lmdb.Transaction, db: Any, image_map: Callable[[int], np.ndarray
                       | None]) -> list[tuple[bytes, bytes]]:
    """Records of a ``(seq_id, image_id)``-keyed database (thumbnails) with the image ids
    renumbered and the dropped frames' records left out; ``image_map(seq)`` is the new image
    id per old one (-1 dropped), None for a sequence that is gone. In key order. O(records)."""
    out = []
    maps: dict[int, np.ndarray | None] = {}
    for key, value in txn.cursor(db=db):
        seq, image = SEQ_IMAGE_KEY.unpack(key)
        if seq not in maps:
            maps[seq] = image_map(seq)
        new = maps[seq]
        if new is None or image >= len(new) or new[image] < 0:
            continue
        out.append((SEQ_IMAGE_KEY.pack(seq, int(new[image])), bytes(value)))
    return out


def reduced_sightings(txn: lmdb.Transaction, env: LmdbEnv, reduction: Reduction,
                      locate: Callable[[int], tuple[int, int]],
                      image_map: Callable[[int], np.ndarray],
                      span_of: Callable[[int], tuple[int, int] | None]
                      ) -> list[tuple[bytes, bytes]]:
    """The sighting records after the summary: each kept vertex's renumbered, each dropped
    vertex's folded into its stand-in's (counts add up, the newest ``last_*`` wins), and one
    sighting of a stand-in per entry of ``reduction.sightings``. ``locate(vertex)`` is the
    ``(seq_id, image_id)`` of an old vertex id (a kept one), ``image_map(seq)`` a kept one's
    new image ids, ``span_of(seq)`` a sequence's old ``(first vertex, length)`` (None if it is
    not in the map: a stray record, left out). Sorted by key. O(records + sightings)."""
    merged: dict[tuple[int, int], tuple[int, float, float, str]] = {}

    def add(seq: int, image: int, count: int, seen: float, dist: float, drive: str) -> None:
        held = merged.get((seq, image))
        if held is not None:
            total = held[0] + count
            if held[1] > seen:
                seen, dist, drive = held[1], held[2], held[3]
            count = total
        merged[(seq, image)] = (min(count, 2**32 - 1), seen, dist, drive)

    if env.has_db(SIGHTINGS_DB):
        for key, value in txn.cursor(db=env.db(SIGHTINGS_DB)):
            s = decode_sighting(bytes(key), bytes(value))
            span = span_of(s.seq_id)
            if span is None or s.image_id >= span[1]:
                continue  # a stray record (check flags it, --repair drops it)
            vertex = span[0] + s.image_id
            target = vertex if reduction.keep[vertex] else int(reduction.redirect[vertex])
            if target < 0:
                continue
            seq, image = locate(target)
            add(seq, image, s.count, s.last_seen, s.last_distance, s.last_drive)
    for vertex, dist, drive, when in reduction.sightings:
        seq, image = locate(int(vertex))
        add(seq, image, 1, when, dist, drive)
    out = []
    for (seq, image), (count, seen, dist, drive) in merged.items():
        new = image_map(seq)
        assert new[image] >= 0  # stand-ins are kept (Reduction.validate)
        out.append((SEQ_IMAGE_KEY.pack(seq, int(new[image])),
                    encode_sighting(count, seen, dist, drive)))
    return sorted(out)


def regroup_all(out: lmdb.Transaction, env: LmdbEnv, seqs: list[SequenceRecord],
                edges: list[tuple[bytes, bytes]]) -> int:
    """Write the union-find, members and component records of ``seqs`` (the new records)
    grouped by ``edges`` (new ids) into ``out``; return the number of components.

    Notes
    -----
    O(S log S + E) with an in-memory union-find.
    """
    ordered = sorted(seqs, key=lambda s: s.first_vertex)
    starts = np.array([s.first_vertex for s in ordered], dtype=np.int64)
    sets = UnionFind(len(ordered))
    if edges:
        ids = np.frombuffer(b"".join(k for k, _ in edges), dtype=">u8").astype(np.int64)
        at = np.searchsorted(starts, ids.reshape(-1, 2), side="right") - 1
        for a, b in np.unique(at, axis=0).tolist():
            sets.union(a, b)
    groups = [[ordered[i] for i in members] for members in sets.groups()]
    for group in groups:
        write_component(out, env, group, prefer=min(s.seq_id for s in group))
    return len(groups)

