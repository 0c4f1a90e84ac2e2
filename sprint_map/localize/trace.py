"""Localisation traces: what the filter saw and believed at every frame of one drive.

``sprint-map localize ... --trace OUT`` and ``sprint-map ingest ... --trace OUT`` attach a
:class:`TraceRecorder` to the :class:`~sprint_map.localize.localizer.Localizer` (its ``observer``
hook); after every frame it keeps

* the frame's retrieval hits (vertex ids and squared-L2 distances, ``k`` per frame),
* the active components and the posterior mass of each,
* the ``top_n`` most probable states (vertices) of the belief and their posterior,
* the causal decision (place, its probability, the unmapped-place probability) and the
  active-set size,

and :meth:`TraceRecorder.save` writes them, with the decisions the command reported (smoothed
ones for ``--smooth`` and ``ingest``, with the merge rule's verdict), as one compressed
``.npz`` written atomically (:class:`~sprint_map.util.output.Output`: never inside the map). Memory and file size are
O(frames * (k + top_n + active components)): bounded per frame, whatever the map's size.

File format (``FORMAT``, ``VERSION`` in its ``meta`` JSON; arrays with ``F`` frames):

=====================  ===========  ==========================================================
key                    shape        meaning
=====================  ===========  ==========================================================
``meta``               ()           JSON text: format, version, map path, k, top_n, frames,
                                    command, source, smoothed
``hit_vertex``         (F, k)       retrieved vertex ids (-1: none)
``hit_seq``            (F, k)       their sequence (-1: none, or since removed)
``hit_image``          (F, k)       their image in that sequence
``hit_dist``           (F, k)       squared-L2 distances (float32)
``top_seq``            (F, top_n)   most probable states, descending (-1 pads)
``top_image``          (F, top_n)
``top_prob``           (F, top_n)   their posterior (float32)
``active_ptr``         (F + 1,)     CSR offsets into ``active_component`` / ``active_mass``
``active_component``   (A,)         active component ids (union-find root sequences)
``active_mass``        (A,)         posterior mass of each (float32)
``n_active_vertices``  (F,)         vertices the step propagated
``dec_seq``            (F,)         causal decision (-1: no match)
``dec_image``          (F,)
``dec_prob``           (F,)         its place probability (float32)
``novel_prob``         (F,)         unmapped-place probability (float32)
``final_seq``          (F,)         the reported decision (smoothed with --smooth / ingest)
``final_image``        (F,)
``final_prob``         (F,)
``merged``             (F,)         ingest: whether the decision became an edge (bool)
=====================  ===========  ==========================================================
"""

from __future__ import annotations

import json
import os
import stat
import zipfile
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from sprint_map.errors import InputError
from sprint_map.util.arrays import Float32Array, Int64Array
from sprint_map.util.output import Output

if TYPE_CHECKING:
    from pathlib import Path

    from sprint_map.localize.localizer import FrameDecision, Localizer
    from sprint_map.storage.records import SequenceRecord

__all__ = ["FORMAT", "MAX_TRACE_BYTES", "TOP_N", "VERSION", "Trace", "TraceRecorder",
           "TracedMap", "read_trace"]

FORMAT = "sprint-map-trace"
VERSION = 1
#: Belief states kept per frame by default.
TOP_N = 8


class TracedMap(Protocol):
    """What a trace reads of the map it was recorded on (:class:`sprint_map.map.SprintMap` is
    one): its path and its sequences, to resolve vertex ids on save."""

    @property
    def path(self) -> Path: ...

    def sequences(self) -> list[SequenceRecord]: ...


class TraceRecorder:
    """Collects one drive's per-frame filter state; attach with :meth:`attach`.

    Parameters
    ----------
    smap : TracedMap
        The map being localised against (vertex ids are resolved against it on save).
    top_n : int
        Belief states kept per frame.

    Notes
    -----
    Per frame: O(live) to pick the top states (``argpartition`` over the live belief) plus
    O(k + active components) kept; nothing when not attached.
    """

    def __init__(self, smap: TracedMap, top_n: int = TOP_N) -> None:
        if top_n < 1:
            raise ValueError("top_n must be >= 1")
        self.map = smap
        self.top_n = top_n
        self.k = 0
        self._localizer: Localizer | None = None
        self._hits: list[tuple[np.ndarray, np.ndarray]] = []
        self._top: list[tuple[np.ndarray, np.ndarray]] = []
        self._active: list[tuple[np.ndarray, np.ndarray]] = []
        self._decisions: list[FrameDecision] = []
        self._n_active: list[int] = []

    def attach(self, localizer: Localizer) -> None:
        """Record every frame ``localizer`` decides from now on (sets its ``observer``)."""
        self._localizer = localizer
        self.k = localizer.search_k
        localizer.observer = self.observe

    @property
    def frames(self) -> int:
        return len(self._decisions)

    def observe(self, decision: FrameDecision, ids: Int64Array, dists: Float32Array) -> None:
        """The localizer's per-frame hook: keep the frame's hits, belief and decision."""
        loc = self._localizer
        if loc is None:
            raise RuntimeError("TraceRecorder.observe before attach()")
        self._hits.append((np.asarray(ids, dtype=np.int64).ravel().copy(),
                           np.asarray(dists, dtype=np.float32).ravel().copy()))
        live, _sink = loc.filter.live_belief() if loc.filter.frames else ([], 1.0)
        vids, probs = [], []
        for trans, slots, vals in live:
            if len(vals):
                keep = _top_indices(vals, self.top_n)
                vids.append(trans.vertex_of_slots(slots[keep]))
                probs.append(vals[keep])
        if vids:
            v, p = np.concatenate(vids), np.concatenate(probs)
            keep = _top_indices(p, self.top_n)
            self._top.append((v[keep], p[keep].astype(np.float32)))
        else:
            self._top.append((np.empty(0, np.int64), np.empty(0, np.float32)))
        masses = loc.filter.component_probs() if loc.filter.frames else {}
        self._active.append((np.fromiter(masses.keys(), np.int64, len(masses)),
                             np.fromiter(masses.values(), np.float32, len(masses))))
        self._n_active.append(int(loc.filter.n_active_vertices) if loc.filter.frames else 0)
        self._decisions.append(decision)

    def save(self, path: str | os.PathLike[str] | Output, *,
             final: Sequence[FrameDecision] | None = None,
             merged: np.ndarray | None = None, meta: dict[str, Any] | None = None) -> None:
        """Write the trace to ``path`` atomically.

        Parameters
        ----------
        path : path or Output
            Where to write; an :class:`~sprint_map.util.output.Output` opened before the drive
            was localised (so an unwritable path is refused before any work) is committed.
        final : decisions, optional
            What the command reported per frame (default: the causal decisions recorded).
        merged : bool array, optional
            The merge rule's verdict per decision (``ingest``).
        meta : dict, optional
            Extra JSON fields (command, source, ...).

        Notes
        -----
        O(F (k + top_n) log S) to resolve vertex ids to ``(sequence, image)`` for S sequences.
        """
        n = self.frames
        final = list(final) if final is not None else self._decisions
        if len(final) != n:
            raise ValueError(f"{len(final)} final decisions for {n} traced frames")
        k = max([self.k, *(len(h[0]) for h in self._hits)])
        hit_v = np.full((n, k), -1, np.int64)
        hit_d = np.full((n, k), np.inf, np.float32)
        top_v = np.full((n, self.top_n), -1, np.int64)
        top_p = np.zeros((n, self.top_n), np.float32)
        for t, ((ids, dists), (tv, tp)) in enumerate(zip(self._hits, self._top, strict=True)):
            hit_v[t, :len(ids)], hit_d[t, :len(dists)] = ids, dists
            order = np.argsort(-tp, kind="stable")
            top_v[t, :len(tv)], top_p[t, :len(tp)] = tv[order], tp[order]
        resolve = _Resolver(self.map)
        hit_s, hit_i = resolve(hit_v)
        top_s, top_i = resolve(top_v)
        ptr = np.zeros(n + 1, np.int64)
        ptr[1:] = np.cumsum([len(a) for a, _ in self._active])
        arrays: dict[str, np.ndarray] = {
            "hit_vertex": hit_v, "hit_seq": hit_s, "hit_image": hit_i, "hit_dist": hit_d,
            "top_seq": top_s, "top_image": top_i, "top_prob": top_p,
            "active_ptr": ptr,
            "active_component": _cat([a for a, _ in self._active], np.int64),
            "active_mass": _cat([m for _, m in self._active], np.float32),
            "n_active_vertices": np.asarray(self._n_active, np.int64),
            "merged": (np.zeros(n, bool) if merged is None or not len(merged)
                       else np.asarray(merged, bool)),
        }
        for prefix, decisions in (("dec", self._decisions), ("final", final)):
            arrays[f"{prefix}_seq"] = np.array([-1 if d.seq_id is None else d.seq_id
                                                for d in decisions], np.int64)
            arrays[f"{prefix}_image"] = np.array([-1 if d.image_id is None else d.image_id
                                                  for d in decisions], np.int64)
            arrays[f"{prefix}_prob"] = np.array([d.prob for d in decisions], np.float32)
        arrays["novel_prob"] = np.array([d.novel_prob for d in self._decisions], np.float32)
        info = {"format": FORMAT, "version": VERSION, "map": str(self.map.path), "k": k,
                "top_n": self.top_n, "frames": n, **(meta or {})}
        arrays["meta"] = np.array(json.dumps(info))

        out = path if isinstance(path, Output) else Output(path, "trace",
                                                            forbidden=[self.map.path])
        with out:
            np.savez_compressed(out.stream, **arrays)  # type: ignore[arg-type]
            out.commit()


@dataclass(frozen=True)
class Trace:
    """A trace file read back: ``meta`` (its JSON) and the arrays of the module table."""

    meta: dict[str, Any]
    arrays: dict[str, np.ndarray]

    @property
    def frames(self) -> int:
        return int(self.meta["frames"])

    def __getitem__(self, key: str) -> np.ndarray:
        return self.arrays[key]

    def active(self, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """``(component ids, masses)`` active after ``frame``."""
        lo, hi = self.arrays["active_ptr"][frame:frame + 2]
        return self.arrays["active_component"][lo:hi], self.arrays["active_mass"][lo:hi]


#: Largest trace read, in bytes of its arrays once loaded (checked from the ``.npy`` headers
#: before anything is decompressed) and of the file itself: a 100,000-frame trace is ~60 MB.
MAX_TRACE_BYTES = 512 * 1024 * 1024
#: Largest ``meta`` JSON text read.
MAX_META_BYTES = 64 * 1024
_INT, _FLOAT, _BOOL = "iu", "f", "biu"
#: Every array of a trace: (dtype kinds, shape in terms of F frames, K hits, T top states and
#: A active entries).
_LAYOUT: dict[str, tuple[str, tuple[str, ...]]] = {
    "hit_vertex": (_INT, ("F", "K")), "hit_seq": (_INT, ("F", "K")),
    "hit_image": (_INT, ("F", "K")), "hit_dist": (_FLOAT, ("F", "K")),
    "top_seq": (_INT, ("F", "T")), "top_image": (_INT, ("F", "T")),
    "top_prob": (_FLOAT, ("F", "T")), "active_ptr": (_INT, ("F+1",)),
    "active_component": (_INT, ("A",)), "active_mass": (_FLOAT, ("A",)),
    "n_active_vertices": (_INT, ("F",)), "dec_seq": (_INT, ("F",)), "dec_image": (_INT, ("F",)),
    "dec_prob": (_FLOAT, ("F",)), "novel_prob": (_FLOAT, ("F",)), "final_seq": (_INT, ("F",)),
    "final_image": (_INT, ("F",)), "final_prob": (_FLOAT, ("F",)), "merged": (_BOOL, ("F",)),
}


def read_trace(path: str | os.PathLike[str], max_bytes: int = MAX_TRACE_BYTES) -> Trace:
    """Read and validate, whole, a trace written by :meth:`TraceRecorder.save`.

    Before anything is decompressed, every member's ``.npy`` header is read: the arrays must
    be the module table's (no object dtype: never a pickle), of at most ``max_bytes`` in all.
    Once loaded, the shapes must agree with ``meta["frames"]``, the CSR offsets must be
    ordered, and every probability and shown distance finite: a trace that is served
    answers every route. O(file size) time, at most ``max_bytes`` memory.

    Raises
    ------
    InputError
        Not a regular file, not an ``.npz`` of this format, damaged, too large, of another
        format or a newer version.
    """
    where = str(path)
    try:
        st = os.stat(path)
    except OSError as exc:
        raise InputError(f"{where}: not a sprint-map trace (cannot read it: "
                         f"{exc.strerror or exc})") from exc
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{where}: not a sprint-map trace (not a regular file)")
    if st.st_size > max_bytes:
        raise InputError(f"{where}: trace of {st.st_size} bytes is larger than the "
                         f"{max_bytes} bytes read")
    try:
        if not zipfile.is_zipfile(path):
            raise InputError(f"{where}: not a sprint-map trace (an .npz file is expected)")
        _check_members(path, max_bytes)
        with np.load(path, allow_pickle=False) as data:
            if "meta" not in data.files:
                raise InputError(f"{where}: not a sprint-map trace (no meta)")
            raw = data["meta"]
            if raw.dtype.kind != "U" or raw.shape != () or len(str(raw)) > MAX_META_BYTES:
                raise InputError(f"{where}: not a sprint-map trace (bad meta)")
            meta = json.loads(str(raw), parse_constant=_no_constant)
            _check_meta(where, meta)
            missing = sorted(set(_LAYOUT) - set(data.files))
            if missing:
                raise InputError(f"{where}: trace lacks {', '.join(missing)}")
            arrays = {key: data[key] for key in _LAYOUT}
    except InputError:
        raise
    except (OSError, ValueError, KeyError, EOFError, RecursionError, zipfile.BadZipFile,
            zlib.error, NotImplementedError) as exc:
        raise InputError(f"{where}: not a sprint-map trace ({type(exc).__name__}: "
                         f"{str(exc)[:200]})") from exc
    _check_arrays(where, meta, arrays)
    return Trace(meta, arrays)


def _check_meta(where: str, meta: Any) -> None:
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise InputError(f"{where}: not a sprint-map trace")
    if not isinstance(meta.get("version"), int) or meta["version"] > VERSION:
        raise InputError(f"{where}: trace version {meta.get('version')} is newer than this "
                         f"sprint-map reads ({VERSION})")


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} in the trace's meta")


def _check_members(path: str | os.PathLike[str], max_bytes: int) -> None:
    """The members' headers: known names, plain dtypes, ``max_bytes`` in all. O(members)."""
    total = 0
    with zipfile.ZipFile(path) as archive:
        infos = archive.infolist()
        if len(infos) > 2 * len(_LAYOUT):
            raise InputError(f"{path}: not a sprint-map trace ({len(infos)} members)")
        for info in infos:
            key = info.filename.removesuffix(".npy")
            if key not in _LAYOUT and key != "meta":
                continue  # never loaded
            with archive.open(info) as fh:
                version = np.lib.format.read_magic(fh)
                if version == (1, 0):
                    shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
                elif version == (2, 0):
                    shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
                else:
                    raise InputError(f"{path}: {key} is of .npy version {version}")
            if dtype.hasobject or dtype.fields is not None:
                raise InputError(f"{path}: {key} holds objects (a trace holds numbers)")
            total += int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
            if total > max_bytes:
                raise InputError(f"{path}: the trace's arrays exceed the {max_bytes} bytes read")


def _check_arrays(where: str, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> None:
    """Shapes, kinds, offsets and finite values (see :func:`read_trace`). O(array sizes)."""
    frames = meta.get("frames")
    if not isinstance(frames, int) or isinstance(frames, bool) or frames < 0:
        raise InputError(f"{where}: bad frame count {frames!r}")
    ptr = arrays["active_ptr"]
    dims = {"F": frames, "F+1": frames + 1, "K": arrays["hit_seq"].shape[-1],
            "T": arrays["top_seq"].shape[-1],
            "A": int(ptr[-1]) if ptr.dtype.kind in _INT and ptr.ndim == 1 and len(ptr) else 0}
    for key, (kinds, shape) in _LAYOUT.items():
        arr = arrays[key]
        if arr.dtype.kind not in kinds or arr.shape != tuple(dims[d] for d in shape):
            raise InputError(f"{where}: trace array {key} is {arr.dtype} {arr.shape}, not of "
                             f"shape ({', '.join(shape)}) with {frames} frames")
    if ptr[0] != 0 or np.any(np.diff(ptr) < 0):
        raise InputError(f"{where}: trace offsets active_ptr are not ordered from 0")
    shown = arrays["hit_seq"] >= 0
    for key in ("top_prob", "active_mass", "dec_prob", "novel_prob", "final_prob"):
        if not np.all(np.isfinite(arrays[key])):
            raise InputError(f"{where}: trace array {key} holds a value that is not finite")
    if not np.all(np.isfinite(arrays["hit_dist"][shown])):
        raise InputError(f"{where}: trace array hit_dist holds a value that is not finite")
    for seq, image in (("top_seq", "top_image"), ("hit_seq", "hit_image"),
                       ("dec_seq", "dec_image"), ("final_seq", "final_image")):
        if np.any(arrays[image][arrays[seq] >= 0] < 0):
            raise InputError(f"{where}: trace array {image} holds a negative image")


class _Resolver:
    """Vertex ids to ``(sequence, image)`` through the map's sequence table (searchsorted)."""

    def __init__(self, smap: TracedMap) -> None:
        seqs = sorted(smap.sequences(), key=lambda s: s.first_vertex)
        self.first = np.array([s.first_vertex for s in seqs], np.int64)
        self.length = np.array([s.length for s in seqs], np.int64)
        self.ids = np.array([s.seq_id for s in seqs], np.int64)

    def __call__(self, vids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        seq = np.full(vids.shape, -1, np.int64)
        image = np.full(vids.shape, -1, np.int64)
        if not len(self.first):
            return seq, image
        pos = np.searchsorted(self.first, vids, side="right") - 1
        ok = (vids >= 0) & (pos >= 0)
        pos = np.clip(pos, 0, None)
        ok &= vids - self.first[pos] < self.length[pos]  # not in a removed range
        seq[ok] = self.ids[pos[ok]]
        image[ok] = (vids - self.first[pos])[ok]
        return seq, image


def _top_indices(values: np.ndarray, n: int) -> np.ndarray:
    if len(values) <= n:
        return np.arange(len(values))
    return np.argpartition(values, -n)[-n:]


def _cat(parts: list[np.ndarray], dtype: type) -> np.ndarray:
    return np.concatenate(parts).astype(dtype) if parts else np.empty(0, dtype)
