"""The live support of a component: windows of slots that hold belief, as vectorised set operations.

Inside an active component the filter only propagates *windows*: half-open slot ranges
``[lo, hi)``, sorted, each inside one sequence, that together cover every slot holding belief
(every slot outside them holds exactly 0). Propagation grows a window by ``W - 1`` slots (the
forward window; clipped at the sequence end, the rest goes to the sink); an edge leaving a window,
or a hit outside every window, opens a new one; trimming (``HMMConfig.support_threshold``) shrinks
them again. Two windows are kept at least ``gap = max(W - 1, 1)`` slots apart, so that one
propagation step never writes the same slot from two windows; closer windows are merged.

Everything here works on a handful of numpy arrays with a fixed number of numpy calls, whatever
the number of windows: the cost is O(live slots), never O(component).
"""

from __future__ import annotations

import numpy as np

__all__ = ["TRIM_EVERY", "insert_sorted", "merge", "merge_gap", "ranges", "runs", "trim"]

_I64 = np.int64
_EMPTY = np.empty(0, dtype=_I64)

#: Windows are trimmed every TRIM_EVERY frames (and grow by W - 1 slots per frame in between).
#: A few more slots per window cost next to nothing in one ``np.correlate``; trimming costs a
#: few numpy calls per component, so doing it every frame would dominate the step.
TRIM_EVERY = 16


def merge_gap(window_len: int) -> int:
    """Smallest slot distance between two windows: ``max(W - 1, 1)``.

    With ``W - 1`` free slots after every window a propagation step (which moves mass at most
    ``W - 1`` slots ahead) never reaches the next window; for ``W = 1`` (no movement) windows
    only have to be disjoint and not touching, so runs stay maximal.
    """
    return max(window_len - 1, 1)


def ranges(starts: np.ndarray, lengths: np.ndarray, total: int | None = None) -> np.ndarray:
    """Concatenation of ``arange(starts[i], starts[i] + lengths[i])`` (int64).

    Notes
    -----
    O(total) with five numpy calls; ``lengths`` must be >= 0.
    """
    if total is None:
        total = int(lengths.sum())
    ends = lengths.cumsum()
    out: np.ndarray = np.arange(total, dtype=_I64) + (starts - (ends - lengths)).repeat(lengths)
    return out


def insert_sorted(idx: np.ndarray, extra: np.ndarray) -> np.ndarray:
    """The sorted union of strictly increasing ``idx`` and a few slots ``extra``.

    Notes
    -----
    O(len(idx) + e log e) for ``e = len(extra)``: binary searches and one scatter into the
    result, about 10 numpy calls. (``np.union1d`` sorts or hashes all of ``idx`` again: ten
    times slower on the hot path; ``np.insert`` is about as slow.)
    """
    extra = np.sort(extra)
    if extra.size > 1 and bool((extra[1:] == extra[:-1]).any()):
        extra = np.unique(extra)
    pos = idx.searchsorted(extra)
    present = pos < idx.size
    present[present] = idx[pos[present]] == extra[present]
    if present.all():
        return idx
    new = ~present
    extra, pos = extra[new], pos[new]
    at = pos + np.arange(extra.size, dtype=_I64)  # where each new slot lands in the union
    out = np.empty(idx.size + extra.size, dtype=_I64)
    kept = np.ones(out.size, dtype=bool)
    kept[at] = False
    out[at] = extra
    out[kept] = idx
    return out


def merge(lo: np.ndarray, hi: np.ndarray, gap: int) -> tuple[np.ndarray, np.ndarray]:
    """Sort windows and merge the ones that overlap or lie fewer than ``gap`` slots apart.

    Parameters
    ----------
    lo, hi : ndarray of int64
        Non-empty windows ``[lo, hi)`` in any order, possibly overlapping.
    gap : int
        :func:`merge_gap`.

    Returns
    -------
    lo, hi : ndarray of int64
        Sorted disjoint windows, consecutive ones at least ``gap`` slots apart.

    Notes
    -----
    O(m log m) for m windows (one argsort), about ten numpy calls. Windows of different
    sequences are never merged: sequences are separated by ``gap`` gutter slots in the slot
    layout (:class:`sprint_map.hmm.transition.ComponentTransition`).
    """
    if lo.size <= 1:
        return lo, hi
    order = lo.argsort(kind="stable")
    lo = lo[order]
    hi = hi[order]
    reach = np.maximum.accumulate(hi)
    new = np.empty(lo.size, dtype=bool)
    new[0] = True
    np.greater_equal(lo[1:], reach[:-1] + gap, out=new[1:])
    starts = new.nonzero()[0]
    if starts.size == lo.size:
        return lo, hi
    stops = np.concatenate((starts[1:] - 1, [lo.size - 1]))
    return lo[starts], reach[stops]


def runs(slots: np.ndarray, gap: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Group sorted slots into windows, breaking where ``gap`` or more slots lie between two.

    Returns
    -------
    lo, hi : ndarray of int64
        The windows ``[first slot of a run, last slot + 1)``.
    first, last : ndarray of int64
        Index (into ``slots``) of the first and last slot of each run.

    Notes
    -----
    O(len(slots)), six numpy calls; ``slots`` must be non-empty and strictly increasing.
    """
    breaks = ((slots[1:] - slots[:-1]) > gap).nonzero()[0]
    first = np.concatenate(([0], breaks + 1))
    last = np.concatenate((breaks, [slots.size - 1]))
    return slots[first], slots[last] + 1, first, last


def trim(x: np.ndarray, lo: np.ndarray, hi: np.ndarray, limit: float, gap: int,
         extra: np.ndarray | None = None
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Rebuild windows from the slots holding at least ``limit``; zero the rest of them.

    A window keeps the slots from its first to its last slot with belief ``>= limit``; it is
    split where ``gap`` (:func:`merge_gap`) or more consecutive slots hold less (or lie outside
    every window), and windows closer than ``gap`` are merged. ``x`` (float64) is the
    component's slot vector (cut slots set to 0 in place); ``lo``, ``hi`` (int64) sorted
    disjoint windows; ``limit <= 0`` trims nothing (the windows are only rebuilt, merging
    ``extra`` in); ``extra`` (int64, optional): slots outside the windows that hold belief (the
    frame's hits), which join the windows.

    Returns ``(lo, hi, live, trimmed)``: the new windows, the slots of the old windows and
    ``extra`` that lie in them (ascending: every slot that can hold belief), and the belief set
    to 0. O(live log live) (a sort only with ``extra``), about 20 numpy calls.
    """
    idx = ranges(lo, hi - lo)
    if extra is not None:
        idx = insert_sorted(idx, extra)
    if not idx.size:
        return _EMPTY, _EMPTY, _EMPTY, 0.0
    if limit <= 0.0:
        if extra is None:
            return lo, hi, idx, 0.0
        new_lo, new_hi, _, _ = runs(idx, gap)
        return new_lo, new_hi, idx, 0.0
    values = x[idx]
    above = (values >= limit).nonzero()[0]
    if above.size == idx.size:
        if extra is None:
            return lo, hi, idx, 0.0
        new_lo, new_hi, _, _ = runs(idx, gap)
        return new_lo, new_hi, idx, 0.0
    if not above.size:
        x[idx] = 0.0
        return _EMPTY, _EMPTY, _EMPTY, float(values.sum())
    new_lo, new_hi, first, last = runs(idx[above], gap)
    # Positions (in idx) kept: from the first to the last above-limit slot of every run.
    marks = np.zeros(idx.size + 1, dtype=np.int8)
    marks[above[first]] = 1
    marks[above[last] + 1] -= 1
    keep = marks.cumsum(dtype=np.int8)[:-1].view(bool)
    cut = ~keep
    x[idx[cut]] = 0.0
    return new_lo, new_hi, idx[keep], float(values[cut].sum())
