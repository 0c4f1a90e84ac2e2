"""``check`` of the segmented index: the manifest, its files, their ids and a sample of codes.

Invariants (area ``index``):

* the manifest parses, its segments are contiguous from vertex 0 and none ends past the map;
* every file it names has its recorded size (torn or padded files are caught by one ``stat``)
  and, when the manifest records checksums (every manifest written since they were added), its
  recorded checksum: bytes overwritten in place are caught too;
* the model is readable, of the map's indexed dimension and the manifest's ``nlist``;
* each segment holds exactly the ids of its range, once each;
* a seeded sample of vertices per segment: the shard row, encoded again with the model, gives
  the very code the segment stores in the very list (encoding is deterministic), so the codes
  are those of the committed rows.

Files the manifest does not name (an interrupted publication) and flat files superseded by the
segments are notes: the next writer's open removes them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map.storage.index.flat import index_files
from sprint_map.storage.index.manifest import (
    MANIFEST,
    Manifest,
    checksum_problems,
    is_segment_file,
    manifest_problems,
    read_manifest,
)
from sprint_map.storage.index.model import Model, gather_rows, read_faiss
from sprint_map.storage.index.projection import Projection
from sprint_map.storage.shards import ShardSet
from sprint_map.storage.store_config import StoreConfig
from sprint_map.util.lazy import faiss  # imported on first use

#: Vertices per segment whose codes are compared with their shard rows re-encoded.
CODE_SAMPLE = 8


def has_segments(directory: Path) -> bool:
    return (directory / MANIFEST).exists()


def list_entries(lists: Any, list_no: int, code_size: int) -> tuple[np.ndarray, np.ndarray]:
    """``(ids, codes (n, code_size) uint8)`` of one inverted list (copied)."""
    n = int(lists.list_size(list_no))
    if not n:
        return np.empty(0, np.int64), np.empty((0, code_size), np.uint8)
    ids = faiss.rev_swig_ptr(lists.get_ids(list_no), n).copy()
    codes = faiss.rev_swig_ptr(lists.get_codes(list_no), n * code_size).copy()
    return ids, codes.reshape(n, code_size)


def segment_ids(index: Any) -> np.ndarray:
    """Every id a segment holds, in list order. O(ntotal)."""
    lists = index.invlists
    parts = [faiss.rev_swig_ptr(lists.get_ids(i), int(lists.list_size(i))).copy()
             for i in range(index.nlist) if lists.list_size(i)]
    return np.concatenate(parts) if parts else np.empty(0, np.int64)


def check_segments(directory: Path, config: StoreConfig, shards: ShardSet, total: int,
                   bad: Callable[[str], None], notes: list[str], checked: dict[str, int],
                   seed: int = 0, live: bool = False,
                   projection: Projection | None = None) -> None:
    """Check the segmented index in ``directory`` against a map of ``total`` vertices.

    ``bad`` records a violation; with ``live`` (a writer holds the lock) a file missing or
    ahead is its publication in flight: a note. ``projection``: the map's learned projection
    the index was built under (``config.dim`` is its output dimension).

    Notes
    -----
    One ``stat`` per file, every file's bytes read once for its checksum (O(index bytes)),
    O(sealed) ids read, O(segments * CODE_SAMPLE) re-encodings.
    """
    try:
        manifest = read_manifest(directory)
    except ValueError as exc:
        bad(f"index manifest {MANIFEST} is unusable: {exc}")
        return
    assert manifest is not None
    model_problem, good, problems = manifest_problems(directory, manifest, total)
    if not model_problem:
        model_bad, sound, bad_bytes = checksum_problems(
            directory, replace(manifest, segments=manifest.segments[:good]), cached=False)
        model_problem = model_bad
        good = min(good, sound)
        problems = problems + bad_bytes
        checked["index_files_checksummed"] = sum(
            1 for _, _, c in manifest.checksummed()[: (2 if manifest.pca_bytes else 1) + good]
            if c)
    for problem in problems:
        if live:
            notes.append(f"index {problem}, in flight")
        else:
            bad(f"index {problem}")
    named = {name for name, _ in manifest.files()} | {MANIFEST}
    for entry in sorted(directory.iterdir()):
        if is_segment_file(entry.name) and entry.name not in named:
            notes.append(f"index file {entry.name} is not in the manifest (an interrupted "
                         "publication; removed by the next writer's open)")
    for _, path in index_files(directory):
        notes.append(f"index file {path.name} is superseded by the segments (removed by the "
                     "next writer's open)")
    if model_problem:
        return
    try:
        model = Model.read(directory, manifest.generation, manifest.kind,
                           bool(manifest.pca_bytes))
    except OSError as exc:
        bad(f"index model is unreadable: {exc}")
        return
    model.projection = projection
    if model.nlist != manifest.nlist or model.ivf.d != config.index_dim:
        bad(f"index model has {model.nlist} lists of dim {model.ivf.d}, the manifest says "
            f"{manifest.nlist} and the map indexes dim {config.index_dim}")
        return
    rng = np.random.default_rng(seed)
    compared = 0
    for seg in manifest.segments[:good]:
        compared += _check_segment(directory, seg, model, shards, total, rng, bad, live)
    if total > manifest.sealed:
        notes.append(f"index tail of {total - manifest.sealed} vertices is searched exactly "
                     "(rebuilt from the shards on load)")
    checked["index_segments"] = good
    checked["index_codes_compared"] = compared


def _check_segment(directory: Path, seg: Any, model: Model, shards: ShardSet, total: int,
                   rng: np.random.Generator, bad: Callable[[str], None], live: bool) -> int:
    try:
        index = read_faiss(directory / seg.file, mmap=True)
    except OSError as exc:
        if not (live and not (directory / seg.file).exists()):
            bad(f"index segment {seg.file} is unreadable: {exc}")
        return 0
    ids = segment_ids(index)
    if len(ids) != seg.stop - seg.start or not np.array_equal(
            np.sort(ids), np.arange(seg.start, seg.stop)):
        bad(f"index segment {seg.file} does not hold exactly vertices {seg.start}.."
            f"{seg.stop - 1}")
        return 0
    sample = np.unique(np.r_[seg.start, seg.stop - 1,
                             rng.integers(seg.start, seg.stop, CODE_SAMPLE)])
    probe: Any = faiss.clone_index(model.ivf)
    probe.add_with_ids(model.transform(gather_rows(shards, sample, total)), sample)
    code_size = int(index.code_size)
    for list_no in range(probe.nlist):
        want_ids, want_codes = list_entries(probe.invlists, list_no, code_size)
        if not len(want_ids):
            continue
        have_ids, have_codes = list_entries(index.invlists, list_no, code_size)
        where = {int(v): i for i, v in enumerate(have_ids)}
        for vid, code in zip(want_ids.tolist(), want_codes, strict=True):
            if vid not in where:
                bad(f"index segment {seg.file}: vertex {vid} is not in the list its shard row "
                    "falls in")
                return len(sample)
            if not np.array_equal(have_codes[where[vid]], code):
                bad(f"index segment {seg.file}: the code of vertex {vid} is not its shard "
                    "row's")
                return len(sample)
    return len(sample)


__all__ = ["Manifest", "check_segments", "has_segments"]
