"""Several drives in one ingest: each its own sequence, committed in order, in groups.

``sprint-map ingest MAP A B C`` (and :meth:`sprint_map.map.SprintMap.ingest_drives`) ingests
drive A, then B against the map that now holds A, then C against A and B: the result equals
three ``ingest`` commands in the same order (same sequences, same edges, same components).
Drives are committed in groups of ``group_drives``, and what a group shares depends on whether
its drives must see each other:

- **Appended** (``merge=False``, ``--no-merge``: no drive is localised, so none needs the
  previous one committed): a real group commit
  (:class:`sprint_map.storage.group_writer.GroupWriter`). Every drive's rows are written, each
  drive validated as it is added, then the shard files are fsynced once and the group's drives
  are recorded in ONE LMDB transaction: the fixed cost of a commit is paid once per group.
  Each drive is still atomic (the transaction holds whole drives only); a kill before the
  commit point leaves none of the group, after it all of it.
- **Localised** (``merge=True``): each drive is localised against the map holding the earlier
  ones, so each is its own commit (rows fsynced once, then its LMDB transaction), and the group
  shares the index persist (:meth:`sprint_map.storage.store.MapStore.group_commit`).

Either way a drive that fails stops the ingest with the drives before it committed (an
appended group commits the drives added before the failing one, then raises), and
``on_committed`` reports each group once it is durable.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from sprint_map.errors import InputError
from sprint_map.hmm.config import HMMConfig
from sprint_map.testing.crash import crash_point
from sprint_map.util.arrays import DescriptorsLike

if TYPE_CHECKING:
    from sprint_map.frontend.centring import DriveCentring
    from sprint_map.localize.localizer import Localizer
    from sprint_map.merge.commit import IngestResult
    from sprint_map.storage.group_writer import GroupWriter

__all__ = ["DEFAULT_GROUP_DRIVES", "Drive", "IngestingMap", "IngestingService", "append_group",
           "ingest_drives"]

#: Drives per group, by default: appended, one transaction; localised, one index persist.
DEFAULT_GROUP_DRIVES = 16


@dataclass(frozen=True)
class Drive:
    """One drive to ingest: its descriptors and what its sequence records.

    ``descriptors`` is an ``(N, dim)`` array or an iterable of ``(n_i, dim)`` batches (e.g.
    ``FrameSource.iter_batches()``, streamed); ``name`` the sequence name (default
    ``seq-<id>``); ``positions`` per-frame ``x, y[, heading]``; ``source`` free text;
    ``fixes`` per-frame GNSS ``x, y[, sigma_m]`` (see :meth:`SprintMap.ingest`).
    """

    descriptors: DescriptorsLike | Iterable[DescriptorsLike]
    name: str | None = None
    positions: np.ndarray | None = None
    source: str = ""
    #: One small JPEG per frame, committed with the drive (see :meth:`SprintMap.ingest`).
    thumbnails: Sequence[bytes] | None = None
    fixes: np.ndarray | None = None


class IngestingService(Protocol):
    """What :func:`ingest_drives` uses of a map's service API
    (:class:`sprint_map.facade.service.MapService` is one): groups of commits, drives' centring."""

    def group_commit(self) -> AbstractContextManager[None]: ...

    def begin_group(self) -> GroupWriter: ...

    def drive_centring(self) -> DriveCentring: ...


class IngestingMap(Protocol):
    """What :func:`ingest_drives` uses of a map open for writing
    (:class:`sprint_map.map.SprintMap` is one)."""

    def ingest(
        self,
        descriptors: DescriptorsLike | Iterable[DescriptorsLike],
        name: str | None = None,
        positions: np.ndarray | None = None,
        *,
        merge: bool = True,
        hmm: HMMConfig | None = None,
        source: str = "",
        observe: Callable[[Localizer], None] | None = None,
        thumbnails: Sequence[bytes] | None = None,
        fixes: np.ndarray | None = None,
    ) -> IngestResult: ...

    @property
    def service(self) -> IngestingService: ...


def ingest_drives(
    smap: IngestingMap,
    drives: Sequence[Drive],
    *,
    merge: bool = True,
    hmm: HMMConfig | None = None,
    group_drives: int = DEFAULT_GROUP_DRIVES,
    on_committed: Callable[[list[IngestResult]], Any] | None = None,
    observe: Callable[[Localizer], None] | None = None,
) -> list[IngestResult]:
    """Ingest ``drives`` in order (see the module docstring); return one result per drive.

    ``group_drives``: drives per group commit (>= 1; 1 makes every drive durable on its own).
    ``on_committed``: called with each group's results once the group is durable.
    ``observe``: given each drive's localizer before its first frame.

    Raises :class:`InputError` when two drives share a name (checked before anything is written)
    or ``group_drives`` < 1, and any error of :meth:`SprintMap.ingest` for the drive that failed:
    the drives before it stay committed, it and the later ones are absent.

    Notes
    -----
    Localised, each drive costs what :meth:`SprintMap.ingest` costs; the index is persisted once
    per group when due. Appended, a group costs O(N * dim) per drive, one fsync per shard file
    written and one LMDB commit.
    """
    if group_drives < 1:
        raise InputError(f"group_drives must be >= 1, got {group_drives}")
    names = [d.name for d in drives if d.name is not None]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise InputError(f"two drives of one ingest are named {dup[0]!r}: give each drive "
                         "its own name")
    results: list[IngestResult] = []
    for start in range(0, len(drives), group_drives):
        group: list[IngestResult] = []
        try:
            with smap.service.group_commit():
                if merge:
                    for i, drive in enumerate(drives[start : start + group_drives]):
                        if i:
                            crash_point("group.between_drives")
                        group.append(smap.ingest(drive.descriptors, name=drive.name,
                                                 positions=drive.positions, merge=merge,
                                                 hmm=hmm, source=drive.source,
                                                 observe=observe,
                                                 thumbnails=drive.thumbnails,
                                                 fixes=drive.fixes))
                else:
                    append_group(smap, drives[start : start + group_drives], group)
        finally:  # the drives committed before a failure are reported too
            results.extend(group)
            if on_committed is not None and group:
                on_committed(group)
    return results


def append_group(smap: IngestingMap, drives: Sequence[Drive], out: list[IngestResult]) -> None:
    """Append ``drives`` without localisation in one group commit; their results go to ``out``.

    Each drive's rows are written and its records validated in turn
    (:meth:`GroupWriter.add <sprint_map.storage.group_writer.GroupWriter.add>`); then one
    fsync of the rows and one LMDB transaction commit them all. A drive that fails is left
    out (its rows truncated): the drives before it are committed, then its error is raised.

    Notes
    -----
    O(N * dim) per drive of N frames, plus one fsync per shard file written and one LMDB
    commit for the whole group.
    """
    from sprint_map.frontend.centring import centre_batches
    from sprint_map.localize.localizer import Timing
    from sprint_map.merge.commit import IngestResult

    failure: Exception | None = None
    with smap.service.begin_group() as writer:
        for i, drive in enumerate(drives):
            if i:
                crash_point("group.between_drives")
            centring = smap.service.drive_centring()

            def stats(c: DriveCentring = centring) -> tuple[int, np.ndarray]:
                return c.stats.frames, c.stats.mean

            try:
                writer.add(centre_batches(centring, drive.descriptors), drive.name,
                           drive.source, drive.positions, thumbnails=drive.thumbnails,
                           stats=stats)
            except Exception as exc:  # the drives before it are still committed
                failure = exc
                break
        added = writer.commit()
    out.extend(IngestResult(a, [], Timing(), name=a.sequence.name, frames=a.sequence.length)
               for a in added)
    if failure is not None:
        raise failure
