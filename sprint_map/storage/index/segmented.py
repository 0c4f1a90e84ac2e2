"""Segmented approximate retrieval: sealed IVF segments per vertex-id range, an exact tail,
exact re-ranking from the shards.

Vertex ids ``[0, sealed)`` are held in sealed *segments*, each an IVF index (PQ or SQ8 codes
of one trained :class:`~sprint_map.storage.index.model.Model`) for one id range ``[a, b)``,
written once, published atomically and opened memory-mapped read-only (``IO_FLAG_MMAP``: the
inverted lists stay in the page cache, not in the heap). Ids ``[sealed, committed)`` are the
*tail*: kept in memory (in the indexed space) and searched exactly. When the tail reaches
``index_segment_rows`` the writer seals it into a new segment; ``index_merge_factor``
segments of one size are merged into one (tiered), so a map of N vertices has
O(merge_factor * log N) segments and adding a sequence never rewrites the index.

A search takes the ``index_rerank`` best candidates of all segments (one IVF search over all
of them: their inverted lists are stacked, ``HStackInvertedLists``) and of the tail, reads
their true float32 rows from the memory-mapped shards and returns the k best by exact squared
L2 distance: the distances are the flat index's, only the candidate set is approximate.

``segments.json``, the manifest (:mod:`~sprint_map.storage.index.manifest`), names the
model and the segments with their sizes and checksums; it is the only thing a reader trusts.
Like the flat index this is a cache of the shards: a segment ahead of LMDB, torn or failing
its checksum is dropped with every segment after it (the tail then starts earlier: its rows
are searched exactly, and the writer seals them again), a bad model drops the whole index (the
writer retrains it). The checksums are verified when an index is loaded (O(index bytes), read
sequentially once per process) and by ``check``; the writer's open only compares sizes (O(1)).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sprint_map.errors import StorageIOError
from sprint_map.storage.index.base import (
    CHUNK,
    IndexNotLoadedError,
    RetrievalIndex,
    padded_results,
)
from sprint_map.storage.index.manifest import (
    MANIFEST,
    Manifest,
    SegmentEntry,
    checksum_bytes,
    checksum_file,
    checksum_problems,
    manifest_problems,
    publish_manifest,
    read_manifest,
    remove_unlisted,
    segment_name,
)
from sprint_map.storage.index.model import (
    APPROX_KINDS,
    MIN_TRAIN,
    Model,
    RowReader,
    gather_rows,
    model_name,
    pca_name,
    publish_bytes,
    read_faiss,
    sample_ids,
    serialize,
    train_model,
    train_sample_size,
    use_threads,
)
from sprint_map.storage.index.projection import Projection
from sprint_map.storage.shards import ShardSet
from sprint_map.storage.store_config import StoreConfig
from sprint_map.testing.crash import crash_point
from sprint_map.util.arrays import Descriptors, SearchResult

if TYPE_CHECKING:
    from concurrent.futures import Future, ThreadPoolExecutor

    import faiss
else:  # imported on first use: commands that only read LMDB never load it
    from sprint_map.util.lazy import faiss

__all__ = ["WITHIN_CACHE", "SegmentedIndex", "tier_plan"]

#: Ranges whose stacked index a searcher keeps (a retrieval shard searches one).
WITHIN_CACHE = 8

def tier_plan(committed: int, rows: int, factor: int, max_rows: int = 0
              ) -> list[tuple[int, int]]:
    """The segments sealing ``[0, committed)`` one ``rows`` block at a time would leave after
    tiered merging: the base-``factor`` digits of ``committed // rows``, largest tier first;
    no merge makes a segment of more than ``max_rows`` (0: no limit), so the top tier holds
    as many segments as it takes.

    >>> [b - a for a, b in tier_plan(10 * 4 + 3, 4, 3)]
    [36, 4]
    >>> [b - a for a, b in tier_plan(10 * 4 + 3, 4, 3, max_rows=12)]
    [12, 12, 12, 4]
    """
    blocks = committed // rows
    sizes: list[int] = []
    top = blocks  # blocks of the largest tier a merge may make: no limit
    if max_rows:
        top = 1
        while rows * top * factor <= max_rows:
            top *= factor
    while blocks:
        if top == 1 or factor ** len(sizes) == top:
            sizes.append(blocks)  # the top tier: every block left, no further merges
            break
        blocks, digit = divmod(blocks, factor)
        sizes.append(digit)
    plan, start = [], 0
    for tier in reversed(range(len(sizes))):
        for _ in range(sizes[tier]):
            stop = start + rows * factor**tier
            plan.append((start, stop))
            start = stop
    return plan


class SegmentedIndex(RetrievalIndex):
    """The segmented approximate index of one map (see the module docstring).

    A :class:`~sprint_map.storage.index.base.RetrievalIndex` (see there for the
    parameters and the contract). :meth:`load` opens the published manifest (False if there
    is none usable: it cannot be built without training, which is :meth:`rebuild`);
    :meth:`rebuild` trains a new generation. Searches re-rank their candidates by exact
    distance, so the distances are exact; only the candidate set is approximate.
    """

    kind = "segmented"
    exact = False
    files = "the segments"

    def __init__(self, directory: Path, config: StoreConfig, *, writable: bool,
                 events: list[str] | None = None, projection: Projection | None = None
                 ) -> None:
        super().__init__(directory, config, writable=writable, events=events,
                         projection=projection)
        self._manifest: Manifest | None = None
        self._model: Model | None = None
        self._segments: list[Any] = []
        self._opened: dict[str, Any] = {}  # segment file -> its memory-mapped index
        self._reader = RowReader()  # re-ranking reads rows with pread, not the memory maps
        self._job: Future[tuple[SegmentEntry, ...]] | None = None  # the sealing worker's
        self._pool: ThreadPoolExecutor | None = None
        self._stacked: Any | None = None
        self._stack_refs: list[Any] = []
        #: the segments and cut of a range -> their stacked index, its refs, its selector
        self._within: dict[tuple[int, int, int, int], tuple[Any, list[Any], Any]] = {}
        self.tail_start = 0
        self._tail = np.empty((0, config.index_dim), dtype=np.float32)
        self.tail_len = 0

    # --- state --------------------------------------------------------------------------------
    @property
    def loaded(self) -> bool:
        return self._manifest is not None

    @property
    def manifest(self) -> Manifest:
        """The manifest of the loaded index (what is published)."""
        if self._manifest is None:
            raise IndexNotLoadedError("the segmented index is not loaded: load() first")
        return self._manifest

    @property
    def model(self) -> Model:
        """The trained model of the loaded index's generation."""
        if self._model is None:
            raise IndexNotLoadedError("the segmented index is not loaded: load() first")
        return self._model

    @property
    def covered(self) -> int:
        return self.tail_start + self.tail_len if self.loaded else 0

    @property
    def persisted(self) -> int:
        return self._manifest.sealed if self._manifest is not None else 0

    @property
    def segments(self) -> tuple[Any, ...]:
        """The open FAISS index of each sealed segment, in vertex order (empty until loaded)."""
        return tuple(self._segments)

    def _published_manifest(self) -> Manifest | None:
        try:
            return read_manifest(self.directory)
        except ValueError:
            return None

    def persisted_on_disk(self) -> int:
        """Vertices the published segments cover (one manifest read; 0 if none usable)."""
        manifest = self._published_manifest()
        return manifest.sealed if manifest is not None else 0

    def has_files(self) -> bool:
        """Whether a manifest is there (usable or not). One ``stat``."""
        return (self.directory / MANIFEST).exists()

    def published(self) -> bool:
        """Whether a manifest that parses is there. One small file read."""
        return self._published_manifest() is not None

    def describe(self) -> dict[str, Any]:
        """Kind, model, segments; loaded, also the tail, training size and code bytes."""
        if self._manifest is None:
            m = self._published_manifest()
            if m is None:
                return {"type": "segmented (none published)"}
            return {"type": f"segmented {m.kind} (IVF{m.nlist})", "generation": m.generation,
                    "segments": len(m.segments), "sealed": m.sealed}
        m = self._manifest
        return {"type": f"segmented {m.kind} (IVF{m.nlist}"
                        f"{', PCA ' + str(self.config.index_dim) if m.pca_bytes else ''})",
                "generation": m.generation, "segments": len(m.segments), "sealed": m.sealed,
                "tail": self.tail_len, "trained_on": m.trained_on,
                "code_bytes": sum(s.bytes for s in m.segments)}

    # --- opening ------------------------------------------------------------------------------
    def discard_untrusted(self, committed: int) -> list[str]:
        """Drop segments ahead of ``committed`` vertices or torn (with every one after them),
        the whole index if its model is, and files the manifest does not name (writer, open).

        Notes
        -----
        One ``stat`` per file: O(segments), O(log map size) with tiered merging.
        """
        actions = []
        try:
            manifest = read_manifest(self.directory)
        except ValueError as exc:
            actions.append(f"removed the index manifest: {exc}")
            manifest = None
        if manifest is not None:
            model_problem, good, problems = manifest_problems(self.directory, manifest,
                                                              committed)
            actions.extend(f"index {problem}: dropped" for problem in problems)
            if model_problem:
                manifest = None
            elif good < len(manifest.segments):
                manifest = replace(manifest, segments=manifest.segments[:good])
                publish_manifest(self.directory, manifest)
        actions.extend(f"removed index {name}: not in the manifest"
                       for name in remove_unlisted(self.directory, manifest))
        return actions

    def load(self, committed: int, shards: ShardSet) -> bool:
        """Open the published index, trusting only what the manifest and the map vouch for,
        and catch its tail up to ``committed``; False if there is no usable manifest or model.

        Segments ahead of ``committed``, torn or failing their checksum are left out (with
        every segment after them: their range joins the tail). A reader may race the writer
        replacing merged segments: it reads the manifest again (three attempts, the last one
        taking what it can).

        Notes
        -----
        O(bytes of the files) to verify their checksums (once per process and file), the
        segments memory-mapped, plus :meth:`catch_up`.
        """
        if self._manifest is None:
            opened = False
            for attempt in range(3):
                opened = self._open(committed, strict=not self.writable and attempt < 2)
                if opened or not (self.directory / MANIFEST).exists():
                    break
            if not opened:
                return False
        self.shards = shards
        self.catch_up(committed, shards)
        return True

    def _open(self, committed: int, *, strict: bool) -> bool:
        """Open the manifest's trusted part; ``strict`` (a reader, which may have read a
        manifest the writer has just replaced): give up on any problem."""
        try:
            manifest = read_manifest(self.directory)
        except ValueError as exc:
            self.events.append(f"index manifest unusable ({exc}); discarded")
            return False
        if manifest is None:
            return False
        model_problem, good, problems = manifest_problems(self.directory, manifest, committed)
        if not model_problem:
            # Bytes corrupted in place (size unchanged): a cache event, like a torn file.
            model_bad, sound, bad_bytes = checksum_problems(
                self.directory, replace(manifest, segments=manifest.segments[:good]))
            model_problem = model_problem or model_bad
            good = min(good, sound)
            problems = bad_bytes + problems
        if strict and problems:
            return False
        self.events.extend(f"index {p}; left out (its vertices are searched exactly from the "
                           "shards and indexed again by the writer)" for p in problems)
        if model_problem:
            return False
        manifest = replace(manifest, segments=manifest.segments[:good])
        try:
            model = Model.read(self.directory, manifest.generation, manifest.kind,
                               bool(manifest.pca_bytes))
            self._start(manifest, model)
        except OSError as exc:
            self._forget()
            if not strict:
                self.events.append(f"index unreadable ({exc}); discarded")
            return False
        return True

    def _start(self, manifest: Manifest, model: Model) -> None:
        """Hold ``model`` and open the segments of ``manifest``; an empty tail after them."""
        model.projection = self.projection
        self._manifest, self._model = manifest, model
        self.tail_start, self.tail_len = manifest.sealed, 0
        self._tail = np.empty((0, self.config.index_dim), dtype=np.float32)
        self._opened = {}
        self._open_segments()

    def _forget(self) -> None:
        self._manifest = self._model = None
        self._segments, self._opened, self._stacked, self._stack_refs = [], {}, None, []
        self._within = {}
        self.tail_start = self.tail_len = 0
        self._tail = np.empty((0, self.config.index_dim), dtype=np.float32)
        self.shards = None
        self._reader.close()

    def _open_segments(self) -> None:
        segments = []
        opened: dict[str, Any] = {}
        for seg in self.manifest.segments:
            if seg.file in self._opened:  # unchanged since the last manifest
                segments.append(self._opened[seg.file])
                opened[seg.file] = segments[-1]
                continue
            index: Any = read_faiss(self.directory / seg.file, mmap=True)
            if index.ntotal != seg.stop - seg.start or index.nlist != self.model.nlist:
                raise OSError(f"{seg.file} holds {index.ntotal} vectors in {index.nlist} lists, "
                              f"not {seg.stop - seg.start} in {self.model.nlist}")
            lists = faiss.downcast_InvertedLists(index.invlists)
            if isinstance(lists, faiss.OnDiskInvertedLists):
                lists.prefetch_nthread = 0  # prefetch threads cost 10x a small search
            table = getattr(index, "precomputed_table", None)
            if table is not None and table.size():
                # Only the stacked index searches (with its own table): a segment's copy of
                # the model's precomputed PQ table (nlist * 256 * pq_m floats, 16 MB at 1,024
                # lists) is dropped; a direct search would compute its tables on the fly.
                index.use_precomputed_table = -1
                table.resize(0)
            segments.append(index)
            opened[seg.file] = index
        self._segments = segments
        self._opened = opened
        self._stacked, self._stack_refs = self._stack(segments)
        self._within = {}

    def _stack(self, segments: list[Any]) -> tuple[Any, list[Any]]:
        """One IVF index over ``segments``' lists (None for none), and what it does not own
        but needs alive. O(segments)."""
        if not segments:
            return None, []
        lists = faiss.InvertedListsPtrVector()  # type: ignore[attr-defined]
        for segment in segments:
            lists.push_back(segment.invlists)
        stacked: Any = faiss.clone_index(self.model.ivf)
        hstack = faiss.HStackInvertedLists(lists.size(), lists.data())
        stacked.replace_invlists(hstack, False)
        stacked.ntotal = sum(int(s.ntotal) for s in segments)
        return stacked, [lists, hstack]  # the stacked index does not own them

    def _stacked_within(self, start: int, stop: int) -> tuple[Any, Any]:
        """The stacked index of the segments that hold ids in ``[start, stop)`` and the search
        parameters that keep only those ids (a selector where a segment reaches past the
        range); cached until the segments change. O(segments) the first time."""
        entries = self.manifest.segments
        inside = [i for i, s in enumerate(entries) if s.start < stop and s.stop > start]
        low = start if inside and entries[inside[0]].start < start else -1
        high = stop if inside and entries[inside[-1]].stop > stop else -1
        # keyed by what is searched: an open-ended range whose stop moves with the commits
        # keeps one entry while the segments stay
        key = (inside[0] if inside else 0, len(inside), low, high)
        if key not in self._within:
            if len(self._within) >= WITHIN_CACHE:
                self._within.clear()
            stacked, refs = self._stack([self._segments[i] for i in inside])
            selector = None
            if low >= 0 or high >= 0:
                selector = faiss.IDSelectorRange(max(low, 0), high if high >= 0 else 1 << 62)
            self._within[key] = (stacked, refs, selector)
        stacked, _, selector = self._within[key]
        if stacked is None:
            return None, None
        if selector is None:
            return stacked, None
        params: Any = faiss.SearchParametersIVF()
        params.sel = selector
        params.nprobe = min(self.config.index_nprobe, stacked.nlist)
        return stacked, params

    def outdated(self) -> bool:
        """A reader whose tail grew past two segments: the writer has sealed them since."""
        return (self.loaded and not self.writable
                and self.tail_len > 2 * self.config.index_segment_rows)

    # --- the tail -----------------------------------------------------------------------------
    def add(self, start: int, rows: Descriptors) -> None:
        """Append ``rows`` (in the indexed space) to the exact tail. O(len(rows) * dim * d)
        for the PCA, amortised O(len(rows) * d) to append."""
        self.require_loaded()
        if start != self.covered:
            raise ValueError(f"index covers {self.covered} vertices, cannot add at {start}")
        self._append_tail(self.model.transform(rows))

    def _append_tail(self, rows: Descriptors) -> None:
        need = self.tail_len + len(rows)
        if need > len(self._tail):
            grown = np.empty((max(need, 2 * len(self._tail), 1024), self._tail.shape[1]),
                             dtype=np.float32)
            grown[: self.tail_len] = self._tail[: self.tail_len]
            self._tail = grown
        self._tail[self.tail_len : need] = rows
        self.tail_len = need

    def _drop_tail_head(self, n: int) -> None:
        keep = self.tail_len - n
        self._tail[:keep] = self._tail[n : self.tail_len].copy()
        self.tail_len = keep
        self.tail_start += n

    # --- search -------------------------------------------------------------------------------
    def search(self, queries: Descriptors, k: int,
               within: tuple[int, int] | None = None) -> SearchResult:
        """k nearest vertices by exact squared L2, among the re-ranked candidates; with
        ``within = (start, stop)`` only among vertex ids ``[start, stop)`` (a retrieval shard's
        range: :mod:`sprint_map.fleet.shards`).

        Notes
        -----
        IVF: one coarse quantization plus ``nprobe`` lists of codes over all segments (within a
        range: over the segments that hold ids of it, the ids of a segment reaching past it
        skipped one by one); tail: O(tail * d); re-ranking: O(max(index_rerank, k) * dim) reads
        from the shards (with a learned projection, also O(rerank * dim * learn_dim) to project
        them).
        """
        shards = self.require_loaded()
        # Every covered row was committed, even when the last load() was an older
        # snapshot's (storage/snapshot.py): re-ranking may read them all.
        committed = self.covered
        raw = np.ascontiguousarray(queries, dtype=np.float32)
        nq = len(raw)
        use_threads(nq)
        n_cand = max(self.config.index_rerank, k)
        # The query in the searched space (float32: only compared), then the model's PCA.
        queries = raw if self.projection is None else self.projection.apply(raw, exact=False)
        reduced = queries if self.model.pca is None else self.model.pca.apply(queries)
        ids = []
        stacked, params = (self._stacked, None) if within is None else self._stacked_within(
            *within)
        if stacked is not None:
            stacked.nprobe = min(self.config.index_nprobe, stacked.nlist)
            ids.append(stacked.search(reduced, n_cand, params=params)[1])
        lo, hi = self.tail_start, self.tail_start + self.tail_len
        if within is not None:
            lo, hi = max(lo, within[0]), min(hi, within[1])
        if hi > lo:
            tail = self._tail[lo - self.tail_start : hi - self.tail_start]
            i = faiss.knn(reduced, tail, min(n_cand, hi - lo))[1]
            ids.append(np.where(i >= 0, i + lo, -1))
        out_d, out_i = padded_results(nq, k)
        if not ids:
            return out_d, out_i
        # Every candidate of the segments and of the tail is re-ranked: their approximate
        # distances (PQ codes, PCA space) are not comparable enough to cut between them.
        cand = np.concatenate(ids, axis=1)
        valid = cand[cand >= 0]
        unique = np.unique(valid)
        rows = self._candidate_rows(shards, unique, committed)
        for q in range(nq):
            mine = cand[q][cand[q] >= 0]
            if not len(mine):
                continue
            diff = rows[np.searchsorted(unique, mine)] - queries[q]
            exact = np.einsum("ij,ij->i", diff, diff)
            order = np.argsort(exact, kind="stable")[:k]
            out_d[q, : len(order)] = exact[order]
            out_i[q, : len(order)] = mine[order]
        return out_d, out_i

    def _candidate_rows(self, shards: ShardSet, ids: np.ndarray, committed: int
                        ) -> Descriptors:
        """The candidates ``ids`` (ascending) in the re-ranking space: the raw rows, or with a
        learned projection the projected ones. Those of the tail are the tail's own rows when
        it holds them in that space (no PCA); the others are read from the shards (and
        projected in float32: they are only compared with each other). O(len(ids)) reads at
        most, plus O(reads * dim * learn_dim) to project them."""
        split = int(np.searchsorted(ids, self.tail_start)) if self.model.pca is None else len(ids)
        tail: Descriptors = self._tail[ids[split:] - self.tail_start]
        if not split:
            return tail
        read = self._reader.rows(shards, ids[:split], committed)
        if self.projection is not None:
            read = self.projection.apply(read, exact=False)
        return read if split == len(ids) else np.concatenate((read, tail))

    # --- writing (the writer only) ------------------------------------------------------------
    def after_commit(self, committed: int, shards: ShardSet) -> bool:
        """Start sealing full tail blocks in the background (never due for the caller)."""
        try:  # sealing runs in a worker thread: the commit path does not wait for it
            self.seal_ready(shards, committed, background=True)
        except OSError as exc:
            raise StorageIOError(f"cannot seal an index segment in {self.directory}: "
                                 f"{exc.strerror or exc}") from exc
        return False

    def persist(self) -> bool:
        """Seal every full tail block now (the worker's block first). O(tail * encode)."""
        if not self.writable or self.shards is None or not self.loaded:
            return False
        self.wait()
        return self.seal_ready(self.shards, self.covered)

    def seal_ready(self, shards: ShardSet, committed: int, *, background: bool = False
                   ) -> bool:
        """Seal full ``index_segment_rows`` blocks of the tail, merging tiers after each.

        In the ``background`` (after a commit) one block at a time is encoded and written by a
        worker thread (FAISS releases the GIL: the commit path does not wait for it) and the
        result installed by a later call; otherwise every full block is sealed now (flush,
        close). Only the calling thread publishes the manifest. Each segment file is
        published before the manifest that names it, so a kill leaves the old manifest (and
        an unlisted file, removed by the next writer's open) or the new one.

        Returns whether a new manifest was published.

        Notes
        -----
        O(segment_rows * nlist * d) to encode a block (the coarse assignment dominates);
        merges copy codes: O(log N) rewrites per vertex.
        """
        self.require_loaded()
        done = self._collect(wait=not background)
        rows = self.config.index_segment_rows
        if background:
            if self._job is None and self.tail_len >= rows:
                # Every full block there is now, in one job: a job behind the writer takes
                # more blocks the next time, so the tail stays O(segment_rows * backlog).
                start = self.tail_start
                blocks = [shards.rows(a, a + rows, committed)
                          for a in range(start, start + self.tail_len - rows + 1, rows)]
                if self._pool is None:  # (imported here: a reader never seals)
                    from concurrent.futures import ThreadPoolExecutor

                    self._pool = ThreadPoolExecutor(1, thread_name_prefix="sprint-map-seal")
                self._job = self._pool.submit(self._seal, self.manifest.segments, blocks,
                                              start, True)
            return done
        while self.tail_len >= rows:
            start = self.tail_start
            self._install(self._seal(self.manifest.segments,
                                     [shards.rows(start, start + rows, committed)], start))
            done = True
        return done

    def _seal(self, segments: tuple[SegmentEntry, ...], blocks: list[Descriptors], start: int,
              worker: bool = False) -> tuple[SegmentEntry, ...]:
        """Encode and publish each of ``blocks`` (ids from ``start`` on) as a segment, merging
        full tiers after each (their files published, not yet named): the segments the next
        manifest names. Touches no state of ``self``."""
        if worker:
            use_threads(1)  # this thread's OpenMP pool: leave the other core to the writer
        factor, cap = self.config.index_merge_factor, self.config.index_segment_max_rows
        for block in blocks:
            segment = faiss.clone_index(self.model.ivf)
            segment.add_with_ids(self.model.transform(block),
                                 np.arange(start, start + len(block), dtype=np.int64))
            segments = segments + (self._publish_segment(segment, start, start + len(block)),)
            crash_point("index.segment_written")
            start += len(block)
            while len(segments) >= factor and len(
                    {s.stop - s.start for s in segments[-factor:]}) == 1 and (
                    not cap or factor * (segments[-1].stop - segments[-1].start) <= cap):
                segments = segments[:-factor] + (self._merge_files(segments[-factor:]),)
        return segments

    def _install(self, segments: tuple[SegmentEntry, ...]) -> None:
        sealed = segments[-1].stop
        self._publish(replace(self.manifest, segments=segments))
        self._drop_tail_head(sealed - self.tail_start)

    def _collect(self, wait: bool) -> bool:
        """Install the worker's segments if it is done (or wait for it); True if installed.

        Raises
        ------
        OSError
            The worker's error (its segment file is unnamed; the block is sealed again later).
        """
        job = self._job
        if job is None or not (wait or job.done()):
            return False
        self._job = None
        self._install(job.result())
        return True

    def wait(self) -> None:
        """Finish the worker's job, if any (before training, merging or closing)."""
        try:
            self._collect(wait=True)
        finally:
            if self._pool is not None:
                self._pool.shutdown()
                self._pool = None

    def _publish_segment(self, segment: Any, start: int, stop: int) -> SegmentEntry:
        name = segment_name(self.manifest.generation, start, stop)
        data = serialize(segment)
        size = publish_bytes(self.directory / name, data)
        return SegmentEntry(start, stop, name, size, checksum_bytes(data))

    def _publish(self, manifest: Manifest) -> None:
        """Publish ``manifest``, open its new segments, delete the files it no longer names."""
        publish_manifest(self.directory, manifest)
        self._manifest = manifest
        self._open_segments()
        remove_unlisted(self.directory, manifest)

    def _merge_files(self, segments: tuple[SegmentEntry, ...]) -> SegmentEntry:
        merged = faiss.clone_index(self.model.ivf)
        for seg in segments:
            # Read into memory: merge_from empties its source, a read-only map cannot be.
            merged.merge_from(read_faiss(self.directory / seg.file), 0)
        entry = self._publish_segment(merged, segments[0].start, segments[-1].stop)
        crash_point("index.segment_written")
        return entry

    def merge(self) -> bool:
        """Merge the sealed segments into as few as ``index_segment_max_rows`` allows: runs of
        consecutive segments, each at most that many vertices (one segment without a limit;
        ``compact``). O(sealed codes)."""
        if not self.loaded:
            return False
        self.wait()
        cap = self.config.index_segment_max_rows
        runs: list[list[SegmentEntry]] = []
        for seg in self.manifest.segments:
            if runs and (not cap or runs[-1][-1].stop - runs[-1][0].start
                         + seg.stop - seg.start <= cap):
                runs[-1].append(seg)
            else:
                runs.append([seg])
        if len(runs) == len(self.manifest.segments):
            return False
        merged = tuple(run[0] if len(run) == 1 else self._merge_files(tuple(run)) for run in runs)
        self._publish(replace(self.manifest, segments=merged))
        return True

    # --- building -----------------------------------------------------------------------------
    def rebuild(self, committed: int, shards: ShardSet, *, publish: bool = True) -> None:
        """Train a new generation's model on a seeded sample, seal ``[0, committed)`` in full
        segments, publish it, then delete the files of older generations.

        The kind is the config's (``ivf-pq`` for ``auto``). Nothing is visible until the
        manifest is replaced, so readers keep the previous index until then; a kill leaves
        the old one (its files named by the old manifest) or the new one. With ``publish``
        False the new generation's files are written but not named: :meth:`finish` names
        them (until then, another index in this directory must not publish a manifest, which
        would delete them as leftovers).

        Raises
        ------
        ValueError
            Fewer than ``MIN_TRAIN`` vertices (too few to train on).

        Notes
        -----
        O(train_sample) rows sampled from the shards, training (see ``train_model``), then
        O(committed) rows encoded.
        """
        assert self.writable
        if committed < MIN_TRAIN:
            raise ValueError(f"an approximate index needs {MIN_TRAIN} vertices to train on, "
                             f"the map has {committed}")
        kind = self.config.index_type if self.config.index_type in APPROX_KINDS else "ivf-pq"
        self.close()
        generation = 1 + max([int(p.name.split(".")[1]) for p in
                              self.directory.glob("model.*.faiss")] + [0])
        config, directory = self.config, self.directory
        sample = gather_rows(shards, sample_ids(committed, train_sample_size(config, committed),
                                                generation), committed)
        model = train_model(config, kind, self.project(sample), committed)
        model.projection = self.projection
        model_bytes, pca_bytes = model.publish(directory, generation)
        crash_point("index.model_trained")
        manifest = Manifest(
            generation, kind, model.nlist, model_bytes, pca_bytes, committed,
            model_checksum=checksum_file(directory / model_name(generation)),
            pca_checksum=checksum_file(directory / pca_name(generation)) if pca_bytes else "")
        self._start(manifest, model)
        entries = []
        for start, stop in tier_plan(committed, config.index_segment_rows,
                                     config.index_merge_factor, config.index_segment_max_rows):
            entries.append(self._publish_segment(self._encode(shards, start, stop, committed),
                                                 start, stop))
            crash_point("index.segment_written")
        self._manifest = replace(manifest, segments=tuple(entries))
        self.tail_start = self.manifest.sealed
        if publish:
            self.finish(committed, shards)

    def finish(self, committed: int, shards: ShardSet) -> None:
        """Publish the manifest of a :meth:`rebuild` made with ``publish=False``, open its
        segments, catch the tail up to ``committed`` and delete every file it does not name
        (the older generations'). O(segments) plus the catch-up."""
        publish_manifest(self.directory, self.manifest)
        self._open_segments()
        self.shards = shards
        self.catch_up(committed, shards)
        remove_unlisted(self.directory, self.manifest)

    def _encode(self, shards: ShardSet, start: int, stop: int, committed: int) -> Any:
        segment = faiss.clone_index(self.model.ivf)
        for lo in range(start, stop, CHUNK):
            hi = min(stop, lo + CHUNK)
            segment.add_with_ids(self.model.transform(shards.rows(lo, hi, committed)),
                                 np.arange(lo, hi, dtype=np.int64))
        return segment

    def remove_files(self) -> list[str]:
        """Delete the manifest, models and segments (every generation)."""
        return remove_unlisted(self.directory, None)

    # --- lifetime -----------------------------------------------------------------------------
    def close(self) -> None:
        """Finish a sealing in flight, then forget the in-memory index. Idempotent."""
        try:
            self.wait()
        finally:
            self._forget()
