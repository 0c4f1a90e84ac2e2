"""Segmented approximate retrieval: sealed IVF segments per vertex-id range, an exact tail,
exact re-ranking from the shards.

Vertex ids ``[0, sealed)`` are held in sealed *segments*, each an IVF index (PQ or SQ8 codes
of one trained :class:`~sprint_map.storage.segment_model.Model`) for one id range ``[a, b)``,
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

``segments.json`` (the manifest, published atomically) names the model, its PCA and the
segments with their byte sizes and checksums (BLAKE2b-128 of the file's bytes; a manifest
written before checksums has none, and its files are trusted on their sizes alone); it is the
only thing a reader trusts. Files it does not name are leftovers of an interrupted publication.
Like the flat index this is a cache of the shards: a segment ahead of LMDB, whose size is not
its recorded size or whose bytes fail their checksum is dropped with every segment after it
(the tail then starts earlier: its rows are searched exactly, and the writer seals them again),
a bad model drops the whole index (the writer retrains it). The checksums are verified when an
index is loaded (O(index bytes), read sequentially once per process) and by ``check``; the
writer's open only compares sizes (O(1)).
"""

from __future__ import annotations

import hashlib
import json
import re
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import faiss
import numpy as np

from sprint_map.config import MapConfig
from sprint_map.storage import atomic
from sprint_map.storage.crash import crash_point
from sprint_map.storage.segment_model import (
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
    use_threads,
)
from sprint_map.storage.shards import ShardSet

MANIFEST = "segments.json"
SEGMENT_RE = re.compile(r"^seg\.(\d{6})\.(\d{12})-(\d{12})\.faiss$")
MODEL_RE = re.compile(r"^(model|pca)\.(\d{6})\.faiss$")
#: Rows read from the shards per batch when filling the tail or encoding a segment.
CHUNK = 65536
#: FAISS's padding distance (``FLT_MAX``), returned with id -1 when fewer than k hits exist.
PAD_DISTANCE = np.finfo(np.float32).max


def segment_name(generation: int, start: int, stop: int) -> str:
    return f"seg.{generation:06d}.{start:012d}-{stop:012d}.faiss"


def is_segment_file(name: str) -> bool:
    """Whether ``name`` belongs to the segmented index (manifest, model, PCA or segment)."""
    return name == MANIFEST or bool(SEGMENT_RE.match(name) or MODEL_RE.match(name))


#: Bytes of a file's checksum (BLAKE2b), hex in the manifest.
CHECKSUM_BYTES = 16
#: Bytes read at a time when checksumming a file.
CHECKSUM_CHUNK = 1 << 20


def checksum_bytes(data: bytes | memoryview) -> str:
    """The manifest checksum of ``data``: BLAKE2b-128, hex. O(len(data))."""
    return hashlib.blake2b(data, digest_size=CHECKSUM_BYTES).hexdigest()


def checksum_file(path: Path) -> str:
    """The manifest checksum of the file ``path`` (read in 1 MiB blocks). O(file size)."""
    digest = hashlib.blake2b(digest_size=CHECKSUM_BYTES)
    with open(path, "rb") as fh:
        while block := fh.read(CHECKSUM_CHUNK):
            digest.update(block)
    return digest.hexdigest()


@dataclass(frozen=True)
class SegmentEntry:
    start: int
    stop: int
    file: str
    bytes: int
    checksum: str = ""  # "": a manifest written before checksums


@dataclass(frozen=True)
class Manifest:
    """What ``segments.json`` records: the model of one generation and its sealed segments."""

    generation: int
    kind: str
    nlist: int
    model_bytes: int
    pca_bytes: int  # 0: no PCA
    trained_on: int  # vertices in the map when the model was trained
    segments: tuple[SegmentEntry, ...] = field(default_factory=tuple)
    model_checksum: str = ""  # "": a manifest written before checksums
    pca_checksum: str = ""

    @property
    def sealed(self) -> int:
        """Vertices covered by the segments (ids ``0..sealed-1``)."""
        return self.segments[-1].stop if self.segments else 0

    def files(self) -> list[tuple[str, int]]:
        """Every file the manifest names, with its recorded size."""
        return [(name, size) for name, size, _ in self.checksummed()]

    def checksummed(self) -> list[tuple[str, int, str]]:
        """Every file the manifest names with its recorded size and checksum ("" if none)."""
        out = [(model_name(self.generation), self.model_bytes, self.model_checksum)]
        if self.pca_bytes:
            out.append((pca_name(self.generation), self.pca_bytes, self.pca_checksum))
        return out + [(s.file, s.bytes, s.checksum) for s in self.segments]

    def encode(self) -> bytes:
        data = asdict(self)
        data["format"] = 1
        return json.dumps(data, indent=1).encode()

    @classmethod
    def decode(cls, raw: bytes) -> Manifest:
        """Parse a manifest; ValueError if it is not one (garbled, torn, another format)."""
        try:
            data: dict[str, Any] = json.loads(raw)
            if data.pop("format") != 1:
                raise ValueError("unknown manifest format")
            segments = tuple(SegmentEntry(**s) for s in data.pop("segments"))
            manifest = cls(**data, segments=segments)
        except (TypeError, KeyError, AttributeError, RecursionError,
                UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ValueError(f"not a segment manifest: {exc}") from exc
        ints = [manifest.generation, manifest.nlist, manifest.model_bytes, manifest.pca_bytes,
                manifest.trained_on] + [v for s in manifest.segments
                                        for v in (s.start, s.stop, s.bytes)]
        texts = [manifest.kind, manifest.model_checksum, manifest.pca_checksum] + [
            v for s in manifest.segments for v in (s.file, s.checksum)]
        if not all(type(v) is int and 0 <= v < 1 << 63 for v in ints) or not all(
                isinstance(v, str) for v in texts):
            raise ValueError("not a segment manifest: a field has the wrong type")
        if any(not SEGMENT_RE.match(seg.file) for seg in manifest.segments):
            raise ValueError("not a segment manifest: a segment file name is not one")
        start = 0
        for seg in manifest.segments:
            if seg.start != start or seg.stop <= seg.start:
                raise ValueError(f"segment {seg.file} does not continue at vertex {start}")
            start = seg.stop
        return manifest


def read_manifest(directory: Path) -> Manifest | None:
    """The manifest in ``directory``, None if there is none; ValueError if it is garbled."""
    try:
        raw = (directory / MANIFEST).read_bytes()
    except FileNotFoundError:
        return None
    return Manifest.decode(raw)


def manifest_problems(directory: Path, manifest: Manifest, committed: int
                      ) -> tuple[str | None, int, list[str]]:
    """Check the files of ``manifest`` against their recorded sizes and the map. One ``stat``
    per file.

    Returns ``(model problem or None, number of trustworthy leading segments, problems)``.
    """

    def problem(name: str, size: int) -> str | None:
        try:
            actual = (directory / name).stat().st_size
        except FileNotFoundError:
            return f"{name} is missing"
        return None if actual == size else f"{name} is torn: {actual} bytes, recorded {size}"

    model_problem = None
    for name, size in manifest.files()[: 2 if manifest.pca_bytes else 1]:
        model_problem = model_problem or problem(name, size)
    problems = [model_problem] if model_problem else []
    good = 0
    for seg in manifest.segments:
        why = (f"{seg.file} is ahead of the map ({committed} vertices)" if seg.stop > committed
               else problem(seg.file, seg.bytes))
        if why:
            problems.append(why)
            break
        good += 1
    return model_problem, good, problems


#: Files this process verified: (path, inode, size, mtime_ns) -> checksum. Published index files
#: are never rewritten in place (a change is a new name), so a reader that reopens the index
#: (it fell behind the writer's segments) re-reads only the new files.
_VERIFIED: dict[tuple[str, int, int, int], str] = {}


def checksum_problems(directory: Path, manifest: Manifest, *, cached: bool = True
                      ) -> tuple[str | None, int, list[str]]:
    """Verify the checksum of every file ``manifest`` records one for (call after
    :func:`manifest_problems`, on the files it trusts).

    Returns ``(model problem or None, number of leading segments whose bytes are sound,
    problems)``, like :func:`manifest_problems`. ``cached``: skip files this process already
    verified, unchanged since (``check`` passes False: it reads every byte).

    Notes
    -----
    O(bytes of the files): each is read once, sequentially (1 MiB blocks).
    """

    def problem(name: str, checksum: str) -> str | None:
        if not checksum:
            return None
        path = directory / name
        try:
            info = path.stat()
            key = (str(path), info.st_ino, info.st_size, info.st_mtime_ns)
            if cached and _VERIFIED.get(key) == checksum:
                return None
            actual = checksum_file(path)
        except FileNotFoundError:
            return f"{name} is missing"
        except OSError as exc:
            return f"{name} is unreadable ({exc.strerror or exc})"
        if actual != checksum:
            return f"{name} fails its checksum (corrupt bytes)"
        _VERIFIED[key] = checksum
        return None

    files = manifest.checksummed()
    model_problem = None
    for name, _, checksum in files[: 2 if manifest.pca_bytes else 1]:
        model_problem = model_problem or problem(name, checksum)
    problems = [model_problem] if model_problem else []
    good = 0
    for seg in manifest.segments:
        why = problem(seg.file, seg.checksum)
        if why:
            problems.append(why)
            break
        good += 1
    return model_problem, good, problems


def tier_plan(committed: int, rows: int, factor: int) -> list[tuple[int, int]]:
    """The segments sealing ``[0, committed)`` one ``rows`` block at a time would leave after
    tiered merging: the base-``factor`` digits of ``committed // rows``, largest tier first."""
    blocks, sizes = committed // rows, []
    while blocks:
        blocks, digit = divmod(blocks, factor)
        sizes.append(digit)
    plan, start = [], 0
    for tier in reversed(range(len(sizes))):
        for _ in range(sizes[tier]):
            stop = start + rows * factor**tier
            plan.append((start, stop))
            start = stop
    return plan


def publish_manifest(directory: Path, manifest: Manifest) -> None:
    publish_bytes(directory / MANIFEST, manifest.encode())
    crash_point("index.manifest_published")


def remove_unlisted(directory: Path, manifest: Manifest | None, keep_flat: bool = True
                    ) -> list[str]:
    """Delete segmented-index files ``manifest`` does not name (all of them if None)."""
    listed = {name for name, _ in manifest.files()} | {MANIFEST} if manifest else set()
    removed = []
    for entry in sorted(directory.iterdir()) if directory.is_dir() else []:
        if is_segment_file(entry.name) and entry.name not in listed:
            atomic.unlink(entry)
            removed.append(entry.name)
    if removed:
        atomic.fsync_dir(directory)
    return removed


class SegmentedIndex:
    """The loaded segmented index of one map (see the module docstring).

    Parameters
    ----------
    directory : Path
        The ``index/`` directory.
    config : MapConfig
        The map's config (segment size, merge factor, nprobe, rerank).
    manifest : Manifest
        What is published (its segments are opened memory-mapped).
    model : Model
        The trained model of ``manifest.generation``.
    """

    def __init__(self, directory: Path, config: MapConfig, manifest: Manifest,
                 model: Model) -> None:
        self.directory = directory
        self.config = config
        self.manifest = manifest
        self.model = model
        self._segments: list[Any] = []
        self._opened: dict[str, Any] = {}  # segment file -> its memory-mapped index
        self._reader = RowReader()  # re-ranking reads rows with pread, not the memory maps
        self._job: Future[tuple[SegmentEntry, ...]] | None = None  # the sealing worker's
        self._pool: ThreadPoolExecutor | None = None
        self._stacked: Any | None = None
        self._stack_refs: list[Any] = []
        self.tail_start = manifest.sealed
        self._tail = np.empty((0, config.index_dim), dtype=np.float32)
        self.tail_len = 0
        self._open_segments()

    # --- opening ----------------------------------------------------------------------------
    @classmethod
    def open(cls, directory: Path, config: MapConfig, committed: int, events: list[str], *,
             strict: bool = False) -> SegmentedIndex | None:
        """Open the published index, trusting only what the manifest and the map vouch for.

        Segments ahead of ``committed`` or torn are left out (with every segment after them:
        their range joins the tail); None if there is no manifest or its model is unusable.
        ``strict`` (a reader, which may have read a manifest the writer has just replaced):
        None on any problem, so that the caller reads the manifest again.
        """
        try:
            manifest = read_manifest(directory)
        except ValueError as exc:
            events.append(f"index manifest unusable ({exc}); discarded")
            return None
        if manifest is None:
            return None
        model_problem, good, problems = manifest_problems(directory, manifest, committed)
        if not model_problem:
            # Bytes corrupted in place (size unchanged): a cache event, like a torn file.
            model_bad, sound, bad_bytes = checksum_problems(
                directory, replace(manifest, segments=manifest.segments[:good]))
            model_problem = model_problem or model_bad
            good = min(good, sound)
            problems = bad_bytes + problems
        if strict and problems:
            return None
        events.extend(f"index {p}; left out (its vertices are searched exactly from the "
                      "shards and indexed again by the writer)" for p in problems)
        if model_problem:
            return None
        manifest = replace(manifest, segments=manifest.segments[:good])
        try:
            model = Model.read(directory, manifest.generation, manifest.kind,
                               bool(manifest.pca_bytes))
            return cls(directory, config, manifest, model)
        except OSError as exc:
            if not strict:
                events.append(f"index unreadable ({exc}); discarded")
            return None

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
            segments.append(index)
            opened[seg.file] = index
        self._segments = segments
        self._opened = opened
        self._stacked = None
        self._stack_refs = []
        if segments:
            lists = faiss.InvertedListsPtrVector()  # type: ignore[attr-defined]
            for segment in segments:
                lists.push_back(segment.invlists)
            stacked: Any = faiss.clone_index(self.model.ivf)
            hstack = faiss.HStackInvertedLists(lists.size(), lists.data())
            stacked.replace_invlists(hstack, False)
            stacked.ntotal = sum(int(s.ntotal) for s in segments)
            self._stacked = stacked
            self._stack_refs = [lists, hstack]  # the stacked index does not own them

    # --- the tail -----------------------------------------------------------------------------
    @property
    def covered(self) -> int:
        return self.tail_start + self.tail_len

    def catch_up(self, committed: int, shards: ShardSet) -> None:
        """Add shard rows ``covered..committed-1`` to the tail. O(rows * dim)."""
        start = self.covered
        while start < committed:
            stop = min(committed, start + CHUNK)
            self._append_tail(self.model.transform(shards.rows(start, stop, committed)))
            start = stop

    def _append_tail(self, rows: np.ndarray) -> None:
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
    def search(self, queries: np.ndarray, k: int, shards: ShardSet, committed: int
               ) -> tuple[np.ndarray, np.ndarray]:
        """k nearest vertices by exact squared L2, among the re-ranked candidates.

        Notes
        -----
        IVF: one coarse quantization plus ``nprobe`` lists of codes over all segments; tail:
        O(tail * d); re-ranking: O(max(index_rerank, k) * dim) reads from the shards.
        """
        queries = np.ascontiguousarray(queries, dtype=np.float32)
        nq = len(queries)
        use_threads(nq)
        n_cand = max(self.config.index_rerank, k)
        reduced = self.model.transform(queries)
        ids = []
        if self._stacked is not None:
            self._stacked.nprobe = min(self.config.index_nprobe, self._stacked.nlist)
            ids.append(self._stacked.search(reduced, n_cand)[1])
        if self.tail_len:
            i = faiss.knn(reduced, self._tail[: self.tail_len], min(n_cand, self.tail_len))[1]
            ids.append(np.where(i >= 0, i + self.tail_start, -1))
        out_d = np.full((nq, k), PAD_DISTANCE, dtype=np.float32)
        out_i = np.full((nq, k), -1, dtype=np.int64)
        if not ids:
            return out_d, out_i
        # Every candidate of the segments and of the tail is re-ranked: their approximate
        # distances (PQ codes, PCA space) are not comparable enough to cut between them.
        cand = np.concatenate(ids, axis=1)
        valid = cand[cand >= 0]
        unique = np.unique(valid)
        rows = self._reader.rows(shards, unique, committed)
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

    # --- writing (the writer only) ------------------------------------------------------------
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
        done = self._collect(wait=not background)
        rows = self.config.index_segment_rows
        if background:
            if self._job is None and self.tail_len >= rows:
                # Every full block there is now, in one job: a job behind the writer takes
                # more blocks the next time, so the tail stays O(segment_rows * backlog).
                start = self.tail_start
                blocks = [shards.rows(a, a + rows, committed)
                          for a in range(start, start + self.tail_len - rows + 1, rows)]
                if self._pool is None:
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

    def _seal(self, segments: tuple[SegmentEntry, ...], blocks: list[np.ndarray], start: int,
              worker: bool = False) -> tuple[SegmentEntry, ...]:
        """Encode and publish each of ``blocks`` (ids from ``start`` on) as a segment, merging
        full tiers after each (their files published, not yet named): the segments the next
        manifest names. Touches no state of ``self``."""
        if worker:
            use_threads(1)  # this thread's OpenMP pool: leave the other core to the writer
        factor = self.config.index_merge_factor
        for block in blocks:
            segment = faiss.clone_index(self.model.ivf)
            segment.add_with_ids(self.model.transform(block),
                                 np.arange(start, start + len(block), dtype=np.int64))
            segments = segments + (self._publish_segment(segment, start, start + len(block)),)
            crash_point("index.segment_written")
            start += len(block)
            while len(segments) >= factor and len(
                    {s.stop - s.start for s in segments[-factor:]}) == 1:
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
        self.manifest = manifest
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

    def merge_all(self) -> bool:
        """Merge every sealed segment into one (``compact``). O(sealed codes)."""
        self.wait()
        if len(self.manifest.segments) < 2:
            return False
        self._publish(replace(self.manifest,
                              segments=(self._merge_files(self.manifest.segments),)))
        return True

    # --- building -----------------------------------------------------------------------------
    @classmethod
    def train(cls, directory: Path, config: MapConfig, kind: str, committed: int,
              shards: ShardSet, generation: int) -> SegmentedIndex:
        """Train a model on a seeded sample, seal ``[0, committed)`` in full segments, publish.

        Nothing is visible until the manifest is replaced (the last step), so readers keep the
        previous index until then; the caller removes what the new manifest does not name.

        Notes
        -----
        O(train_sample) rows sampled from the shards, training (see ``train_model``), then
        O(committed) rows encoded.
        """
        sample = gather_rows(shards, sample_ids(committed, config.index_train_sample,
                                                generation), committed)
        model = train_model(config, kind, sample)
        model_bytes, pca_bytes = model.publish(directory, generation)
        crash_point("index.model_trained")
        manifest = Manifest(
            generation, kind, model.nlist, model_bytes, pca_bytes, committed,
            model_checksum=checksum_file(directory / model_name(generation)),
            pca_checksum=checksum_file(directory / pca_name(generation)) if pca_bytes else "")
        index = cls(directory, config, manifest, model)
        entries = []
        for start, stop in tier_plan(committed, config.index_segment_rows,
                                     config.index_merge_factor):
            entries.append(index._publish_segment(index._encode(shards, start, stop, committed),
                                                  start, stop))
            crash_point("index.segment_written")
        index.manifest = replace(manifest, segments=tuple(entries))
        index.tail_start = index.manifest.sealed
        publish_manifest(directory, index.manifest)
        index._open_segments()
        index.catch_up(committed, shards)
        return index

    def _encode(self, shards: ShardSet, start: int, stop: int, committed: int
                ) -> Any:
        segment = faiss.clone_index(self.model.ivf)
        for lo in range(start, stop, CHUNK):
            hi = min(stop, lo + CHUNK)
            segment.add_with_ids(self.model.transform(shards.rows(lo, hi, committed)),
                                 np.arange(lo, hi, dtype=np.int64))
        return segment

    def describe(self) -> dict[str, Any]:
        m = self.manifest
        return {"type": f"segmented {m.kind} (IVF{m.nlist}"
                        f"{', PCA ' + str(self.config.index_dim) if m.pca_bytes else ''})",
                "generation": m.generation, "segments": len(m.segments), "sealed": m.sealed,
                "tail": self.tail_len, "trained_on": m.trained_on,
                "code_bytes": sum(s.bytes for s in m.segments)}
