"""Several drives in one ingest: each its own sequence, localised and committed in order.

``sprint-map ingest MAP A B C`` (and :meth:`sprint_map.map.SprintMap.ingest_drives`) ingests
drive A, then B against the map that now holds A, then C against A and B: the result equals
three ``ingest`` commands in the same order (same sequences, same edges, same components). Each
drive is its own atomic commit; what the drives of a *group* share is the durability cost
(:meth:`sprint_map.storage.store.MapStore.group_commit`): the per-batch fsyncs of a lone drive
become one fsync of its rows, and the LMDB meta page and the index are made durable once per
group. A crash between two drives leaves the earlier ones committed and the later ones absent.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from sprint_map.arrays import DescriptorsLike
from sprint_map.errors import InputError
from sprint_map.hmm.config import HMMConfig
from sprint_map.storage.crash import crash_point

if TYPE_CHECKING:
    from sprint_map.commit import IngestResult
    from sprint_map.localizer import Localizer

__all__ = ["DEFAULT_GROUP_DRIVES", "Drive", "IngestingMap", "ingest_drives"]

#: Drives whose durability (fsyncs) is paid together, by default.
DEFAULT_GROUP_DRIVES = 16


@dataclass(frozen=True)
class Drive:
    """One drive to ingest: its descriptors and what its sequence records.

    ``descriptors`` is an ``(N, dim)`` array or an iterable of ``(n_i, dim)`` batches (e.g.
    ``FrameSource.iter_batches()``, streamed); ``name`` the sequence name (default
    ``seq-<id>``); ``positions`` per-frame ``x, y[, heading]``; ``source`` free text.
    """

    descriptors: DescriptorsLike | Iterable[DescriptorsLike]
    name: str | None = None
    positions: np.ndarray | None = None
    source: str = ""
    #: One small JPEG per frame, committed with the drive (see :meth:`SprintMap.ingest`).
    thumbnails: Sequence[bytes] | None = None


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
    ) -> IngestResult: ...

    def group_commit(self) -> AbstractContextManager[None]: ...


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

    Parameters
    ----------
    group_drives : int
        Drives per group commit (>= 1; 1 makes every drive durable on its own).
    on_committed : callable, optional
        Called with the results of each group once the group is durable (e.g. to report
        progress: a later failure does not undo them).
    observe : callable, optional
        Given each drive's localizer before its first frame (see :meth:`SprintMap.ingest`).

    Raises
    ------
    InputError
        Two drives of the call have the same name (checked before anything is written), or
        ``group_drives`` < 1.
    Any error of :meth:`SprintMap.ingest`
        For the drive that failed: the drives before it stay committed (and durable), that
        drive and the later ones are absent.

    Notes
    -----
    Each drive costs what :meth:`SprintMap.ingest` costs, less the fsyncs the group shares:
    per drive one fsync of its rows and one of the LMDB pages, per group one of the LMDB meta
    page (and an index persist, when due).
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
            with smap.group_commit():
                for i, drive in enumerate(drives[start : start + group_drives]):
                    if i:
                        crash_point("group.between_drives")
                    group.append(smap.ingest(drive.descriptors, name=drive.name,
                                             positions=drive.positions, merge=merge, hmm=hmm,
                                             source=drive.source, observe=observe,
                                             thumbnails=drive.thumbnails))
        finally:  # the drives committed before a failure are reported too
            results.extend(group)
            if on_committed is not None and group:
                on_committed(group)
    return results
