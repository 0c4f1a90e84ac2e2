"""The published files of the segmented index: their names, the manifest that vouches for
them, and the checks that decide which of them a process may trust.

``segments.json`` (the manifest, published atomically) names the model, its PCA and the
segments with their byte sizes and checksums (BLAKE2b-128 of the file's bytes; a manifest
written before checksums has none, and its files are trusted on their sizes alone); it is the
only thing a reader trusts. Files it does not name are leftovers of an interrupted publication
(:func:`remove_unlisted`). A segment ahead of LMDB, whose size is not its recorded size
(:func:`manifest_problems`, one ``stat`` each) or whose bytes fail their checksum
(:func:`checksum_problems`, O(bytes)) is not trusted, nor is any segment after it.
"""

from __future__ import annotations

import json
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from sprint_map.storage.index.model import model_name, pca_name, publish_bytes
from sprint_map.testing.crash import crash_point
from sprint_map.util import atomic

__all__ = [
    "CHECKSUM_BYTES", "MANIFEST", "MODEL_RE", "SEGMENT_RE", "Manifest", "SegmentEntry",
    "checksum_bytes", "checksum_file", "checksum_problems", "is_segment_file",
    "manifest_problems", "publish_manifest", "read_manifest", "remove_unlisted", "segment_name",
]

MANIFEST = "segments.json"
SEGMENT_RE = re.compile(r"^seg\.(\d{6})\.(\d{12})-(\d{12})\.faiss$")
MODEL_RE = re.compile(r"^(model|pca)\.(\d{6})\.faiss$")


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
    import hashlib  # (here: commands that only read a map never load OpenSSL)

    return hashlib.blake2b(data, digest_size=CHECKSUM_BYTES).hexdigest()


def checksum_file(path: Path) -> str:
    """The manifest checksum of the file ``path`` (read in 1 MiB blocks). O(file size)."""
    import hashlib

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

