"""Frame sources: a directory of images, a video file or a ``.npy`` of descriptors, as a stream.

:func:`open_source` inspects a path and returns a :class:`FrameSource` whose
:meth:`~FrameSource.iter_batches` yields ``(n, dim)`` float32 descriptor batches in frame order.
Images are decoded and described in parallel (see :mod:`sprint_map.frontend.parallel`); a video
is decoded sequentially (a decoder is inherently sequential) and described in parallel; a
``.npy`` is memory-mapped and streamed. Memory is bounded by ``batch_size`` plus a few chunks in
flight per worker, never by the length of the source.

Errors about the input are raised as :class:`~sprint_map.errors.InputError` (or
:class:`~sprint_map.errors.DescriptorShapeError` / :class:`~sprint_map.errors.InvalidDescriptorError`
for a ``.npy`` of the wrong shape or with non-finite values) with a one-line message that starts
with the offending file. Listing and ``.npy`` validation happen in :func:`open_source`, so a bad
source fails before any work is done; an image that does not decode can only be found while
decoding, so it fails the iteration.
"""

from __future__ import annotations

import functools
import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sprint_map.errors import (
    DescriptorShapeError,
    EmptySequenceError,
    InputError,
    InvalidDescriptorError,
)
from sprint_map.frontend.bags import (
    BagOptions,
    bag_index,
    describe_partial,
    is_bag,
    iter_image_messages,
    open_reader,
)
from sprint_map.frontend.descriptors import DescriptorSpec
from sprint_map.frontend.image_path import describe_files
from sprint_map.frontend.imagefiles import is_video_name, list_images
from sprint_map.frontend.parallel import EXECUTORS, default_workers, ordered_map
from sprint_map.frontend.positions import Positions, read_positions
from sprint_map.util.arrays import Descriptors, DescriptorsLike, Image
from sprint_map.util.validation import descriptor_problem

if TYPE_CHECKING:  # OpenCV loads with the first image or video, not for a .npy
    import cv2
from sprint_map.frontend.thumbnails import make_thumbnail, thumbnail_of_file
from sprint_map.frontend.vpr import is_vpr_folder, vpr_order, vpr_positions

__all__ = ["SOURCE_KINDS", "BagSource", "FrameSource", "ImageDirSource", "NpySource",
           "ProgressCallback", "VideoSource", "drive_names", "drive_positions", "open_source",
           "own_positions"]

#: ``progress(frames_done, total_or_None)``, called after each batch.
ProgressCallback = Callable[[int, int | None], None]

SOURCE_KINDS = ("images", "video", "npy", "bag")

# Frames per task handed to a worker: large enough to amortise task overhead (~50 us per
# future), small enough to balance two workers on a short directory.
_MAX_CHUNK = 32


@dataclass(frozen=True)
class _Options:
    stride: int
    batch_size: int
    workers: int
    executor: str
    progress: ProgressCallback | None
    thumbnails: bool = False


class FrameSource(ABC):
    """A sequence of frames, delivered as descriptor batches. Build one with :func:`open_source`.

    - ``kind``: ``"images"``, ``"video"`` or ``"npy"``; ``path``: the directory or file.
    - ``name``: default sequence name (the directory name, or the file name without extension).
    - ``spec``: how frames are described (:class:`DescriptorSpec`; ``None`` for a ``.npy``,
      which holds descriptors already); ``dim``: descriptor dimension.
    - ``count``: frames :meth:`iter_batches` will yield (after ``stride``), or ``None`` when
      unknown before reading (a video: container frame counts are estimates).
    - ``stride``: every ``stride``-th frame is kept, from the first; ``batch_size``: rows per
      batch (the last may be shorter); ``workers``: parallel decode/describe workers.
    - ``progress``: default progress callback of :meth:`iter_batches`.
    - ``thumbnails``: with ``thumbnails=True`` (images and video only), one small JPEG per
      frame (:mod:`sprint_map.frontend.thumbnails`), appended in frame order while
      :meth:`iter_batches` runs (complete once it has ended); ``None`` otherwise.
    """

    kind: str

    def __init__(
        self, path: Path, spec: DescriptorSpec | None, dim: int, options: _Options
    ) -> None:
        self.path = path
        self.name = path.stem if path.is_file() else path.resolve().name
        self.spec = spec
        self.dim = dim
        self.stride = options.stride
        self.batch_size = options.batch_size
        self.workers = options.workers
        self.executor = options.executor
        self.progress = options.progress
        self.thumbnails: list[bytes] | None = [] if options.thumbnails else None
        #: Positions the source itself carries (a bag's GNSS), else None.
        self.positions: Positions | None = None
        #: What a user should know about the source: about the frames read so far (complete
        #: once :meth:`iter_batches` has ended; e.g. images of several sizes in one drive) and
        #: what opening it found (a bag's fixes it could not use).
        self.warnings: list[str] = []

    @property
    @abstractmethod
    def count(self) -> int | None:
        """Frames the source yields, or ``None`` if unknown until read."""

    @property
    def source_frames(self) -> int | None:
        """Frames of the source before any selection (``stride``, a bag's ``--every-m``), as
        a positions file numbers them; ``None`` when unknown before reading (a video)."""
        return None if self.count is None else self.count * self.stride

    @property
    def ordinals(self) -> np.ndarray | None:
        """``(count,)`` int64: the number of each frame yielded among the source's frames
        (its *source ordinal*: ``0, stride, ...``, or the frames ``--every-m`` kept), by
        which positions, times and thumbnails are aligned; ``None`` for a video."""
        return None if self.count is None else np.arange(self.count, dtype=np.int64) * self.stride

    @abstractmethod
    def _batches(self) -> Iterator[Descriptors]:
        """Yield the float32 batches (without progress reporting)."""

    def iter_batches(self, progress: ProgressCallback | None = None) -> Iterator[Descriptors]:
        """Yield ``(n, dim)`` float32 descriptor batches in frame order.

        Parameters
        ----------
        progress : callable, optional
            Called as ``progress(frames_done, total)`` after each batch (``total`` is
            :attr:`count`, ``None`` for a video); defaults to :attr:`progress`.

        Raises
        ------
        InputError
            On a frame that cannot be read or decoded, or a video that yields no frame.
        """
        report = progress if progress is not None else self.progress
        done = 0
        for batch in self._batches():
            done += len(batch)
            if report is not None:
                report(done, self.count)
            yield batch

    def read_all(self, progress: ProgressCallback | None = None) -> Descriptors:
        """Return all descriptors as one ``(count, dim)`` float32 array.

        Holds the whole sequence in memory (``count * dim * 4`` bytes); prefer
        :meth:`iter_batches` for long sources.
        """
        batches = list(self.iter_batches(progress))
        if not batches:
            return np.empty((0, self.dim), dtype=np.float32)
        return np.concatenate(batches)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(path={str(self.path)!r}, kind={self.kind!r}, "
            f"count={self.count}, dim={self.dim}, stride={self.stride})"
        )


def _single_threaded_opencv() -> None:
    """Worker-process initialiser: each process is already one of N parallel workers, so
    OpenCV's own thread pool (used by ``resize``) would only oversubscribe the cores."""
    import cv2

    cv2.setNumThreads(1)


def _describe_files(spec: DescriptorSpec, paths: list[Path]
                    ) -> tuple[Descriptors, list[bytes], list[tuple[int, int]]]:
    """Decode and describe a chunk of image files (runs in a worker); no thumbnails; each
    image's ``(width, height)``."""
    rows, images, _ = describe_files(spec, paths)
    return rows, [], [(image.shape[1], image.shape[0]) for image in images]


def _describe_files_thumbnails(spec: DescriptorSpec, paths: list[Path]
                               ) -> tuple[Descriptors, list[bytes], list[tuple[int, int]]]:
    """:func:`_describe_files` plus each file's thumbnail (the same gray decode describes it)."""
    rows, images, blobs = describe_files(spec, paths)
    return rows, [thumbnail_of_file(data, str(path), image.shape[1], image.shape[0])
                  for path, image, data in zip(paths, images, blobs, strict=True)], [
                      (image.shape[1], image.shape[0]) for image in images]


def _describe_frames(spec: DescriptorSpec, frames: list[Image]) -> Descriptors:
    """Describe a chunk of decoded video frames (runs in a worker thread)."""
    return spec.describe_batch(frames)


def _describe_frames_thumbnails(spec: DescriptorSpec, frames: list[Image]
                                ) -> tuple[Descriptors, list[bytes]]:
    """:func:`_describe_frames` plus each frame's thumbnail."""
    return spec.describe_batch(frames), [make_thumbnail(frame) for frame in frames]


def mixed_sizes(path: Path, sizes: dict[tuple[int, int], list[int]]) -> str:
    """The warning for a drive whose images have several sizes (``(width, height) -> [frames,
    first frame]``): two cameras in one folder, or a resized stretch; each is described at the
    descriptor's own size, so nothing fails, but one drive should be one camera."""
    parts = ", ".join(f"{w}x{h}: {n} frame(s) from frame {first}"
                      for (w, h), (n, first) in sorted(sizes.items(), key=lambda kv: kv[1][1]))
    return (f"{path}: images of {len(sizes)} sizes in one drive ({parts}); two cameras in one "
            "folder? Give each camera its own drive")


def _keep_thumbnails(results: Iterator[tuple[Descriptors, list[bytes]]], sink: list[bytes]
                     ) -> Iterator[Descriptors]:
    """The descriptor chunks of ``results``, their thumbnails appended to ``sink`` in order."""
    for rows, thumbs in results:
        sink.extend(thumbs)
        yield rows


def _named_frames(chunks: Iterator[Descriptors], where: Callable[[int], str]
                  ) -> Iterator[Descriptors]:
    """``chunks``, a refused one's :class:`InvalidDescriptorError` re-raised naming its frame:
    ``where(frame)``, the rows of the chunks before it counted."""
    received = 0
    while True:
        try:
            chunk = next(chunks)
        except StopIteration:
            return
        except InvalidDescriptorError as exc:
            if exc.row is None:
                raise
            raise InvalidDescriptorError(f"{where(received + exc.row)}: {exc.detail}") from None
        received += len(chunk)
        yield chunk


def _chunk_size(n_frames: int | None, batch_size: int, workers: int) -> int:
    if n_frames is None:
        return max(1, min(_MAX_CHUNK, batch_size))
    # At least ~4 chunks per worker so the tail of the directory still keeps every worker busy.
    return max(1, min(_MAX_CHUNK, batch_size, math.ceil(n_frames / (4 * workers))))


def _rebatch(chunks: Iterator[Descriptors], batch_size: int,
             where: Callable[[int], str]) -> Iterator[Descriptors]:
    """Regroup arrays of any lengths into batches of exactly ``batch_size`` rows (last: fewer).

    A chunk whose description was refused (:class:`InvalidDescriptorError` with the ``row``
    of the chunk it names) is reported as the source's frame: ``where(frame)`` and why.
    """
    buffer: list[Descriptors] = []
    held = 0
    for chunk in _named_frames(chunks, where):
        buffer.append(chunk)
        held += len(chunk)
        while held >= batch_size:
            merged = np.concatenate(buffer) if len(buffer) > 1 else buffer[0]
            yield merged[:batch_size]
            rest = merged[batch_size:]
            buffer = [rest] if len(rest) else []
            held = len(rest)
    if held:
        yield np.concatenate(buffer) if len(buffer) > 1 else buffer[0]


class ImageDirSource(FrameSource):
    """Images of one directory, in natural file-name order."""

    kind = "images"

    def __init__(self, path: Path, spec: DescriptorSpec, options: _Options) -> None:
        super().__init__(path, spec, spec.dim, options)
        files = list_images(path)
        #: How the files are ordered: natural file-name order, or the timestamps of
        #: VPR-layout names (:mod:`sprint_map.frontend.vpr`), which also give positions.
        self.order = "file name"
        if is_vpr_folder(files):  # the rule VprDataset applies too
            files, self.order = vpr_order(files)
            kept = np.arange(0, len(files), self.stride)
            self.positions = vpr_positions(files).subset(kept)
            self.positions = Positions(kept, self.positions.xy, time=self.positions.time,
                                       geographic=True)
        self.files: list[Path] = files[:: self.stride]
        self._source_frames = len(files)

    @property
    def count(self) -> int:
        return len(self.files)

    @property
    def source_frames(self) -> int:
        return self._source_frames

    def _batches(self) -> Iterator[Descriptors]:
        assert self.spec is not None
        size = _chunk_size(len(self.files), self.batch_size, self.workers)
        chunks = [self.files[i : i + size] for i in range(0, len(self.files), size)]
        initializer = _single_threaded_opencv if self.executor == "process" else None
        describe = _describe_files if self.thumbnails is None else _describe_files_thumbnails
        sink: list[bytes] = [] if self.thumbnails is None else self.thumbnails
        sink.clear()
        self.warnings.clear()
        sizes: dict[tuple[int, int], list[int]] = {}  # (width, height) -> [frames, first]
        results = ordered_map(functools.partial(describe, self.spec), chunks, self.workers,
                              self.executor, initializer=initializer)

        def kept() -> Iterator[Descriptors]:
            frame = 0
            for rows, thumbs, shapes in results:
                sink.extend(thumbs)
                for shape in shapes:
                    seen = sizes.setdefault(shape, [0, frame])
                    seen[0] += 1
                    frame += 1
                yield rows

        yield from _rebatch(kept(), self.batch_size,
                            lambda i: f"{self.path}: frame {i} ({self.files[i].name})")
        if len(sizes) > 1:
            self.warnings.append(mixed_sizes(self.path, sizes))


def _cv2() -> Any:
    """OpenCV, imported on first use (a source of precomputed descriptors never needs it)."""
    import cv2

    return cv2


class VideoSource(FrameSource):
    """Frames of a video file read with ``cv2.VideoCapture``.

    Decoding runs in the calling thread (it is sequential by nature; FFmpeg may use its own
    threads); frames skipped by ``stride`` are only ``grab()``-ed, not converted. Describing runs
    in worker threads: shipping full frames to processes would cost more than describing them.
    """

    kind = "video"

    def __init__(self, path: Path, spec: DescriptorSpec, options: _Options) -> None:
        super().__init__(path, spec, spec.dim, options)
        capture = self._open()
        try:
            if not capture.grab():
                raise InputError(f"{path}: video has no frames")
            frames = capture.get(_cv2().CAP_PROP_FRAME_COUNT)
        finally:
            capture.release()
        #: Frame count from the container header after ``stride``; only an estimate (0 if
        #: unknown), for progress display.
        self.estimated_count = math.ceil(frames / self.stride) if frames > 0 else 0

    @property
    def count(self) -> None:
        return None

    def _open(self) -> cv2.VideoCapture:
        capture: cv2.VideoCapture = _cv2().VideoCapture(str(self.path))
        if not capture.isOpened():
            capture.release()
            raise InputError(f"{self.path}: cannot open video (unsupported or corrupt file)")
        return capture

    def _frames(self, capture: cv2.VideoCapture, chunk: int) -> Iterator[list[Image]]:
        index = 0
        frames: list[Image] = []
        while True:
            if index % self.stride == 0:
                ok, frame = capture.read()
                if not ok or frame is None:
                    break
                frames.append(frame)
                if len(frames) == chunk:
                    yield frames
                    frames = []
            elif not capture.grab():
                break
            index += 1
        if frames:
            yield frames

    def _batches(self) -> Iterator[Descriptors]:
        assert self.spec is not None
        capture = self._open()
        try:
            chunk = _chunk_size(None, self.batch_size, self.workers)
            frames = self._frames(capture, chunk)
            results: Iterator[Descriptors]
            if self.thumbnails is None:
                results = ordered_map(functools.partial(_describe_frames, self.spec), frames,
                                      self.workers, "thread")
            else:
                self.thumbnails.clear()
                results = _keep_thumbnails(ordered_map(
                    functools.partial(_describe_frames_thumbnails, self.spec), frames,
                    self.workers, "thread"), self.thumbnails)
            produced = 0
            for batch in _rebatch(results, self.batch_size, lambda i: f"{self.path}: frame {i}"):
                produced += len(batch)
                yield batch
            if produced == 0:
                raise InputError(f"{self.path}: video yielded no frames")
        finally:
            capture.release()


class BagSource(FrameSource):
    """The images of one topic of a ROS 1 bag, a ROS 2 bag or an MCAP file, with the
    positions of its GNSS topic (:mod:`sprint_map.frontend.bags`: an index pass when opened,
    then the frames streamed, described by worker threads).

    Attributes
    ----------
    positions : Positions or None
        Latitude/longitude of each kept frame (NaN: no fix), None without a GNSS topic.
    image_topic, gnss_topic : str, str or None
    """

    kind = "bag"

    def __init__(self, path: Path, spec: DescriptorSpec, options: _Options,
                 bag: BagOptions) -> None:
        super().__init__(path, spec, spec.dim, options)
        reader = open_reader(path)
        try:
            self.index = bag_index(path, reader, bag, self.stride)
        finally:
            reader.close()
        self.positions = self.index.positions
        self.warnings.extend(self.index.warnings)
        self.image_topic, self.gnss_topic = self.index.image_topic, self.index.gnss_topic

    @property
    def count(self) -> int:
        return len(self.index.ordinals)

    @property
    def source_frames(self) -> int:
        return self.index.image_count

    @property
    def ordinals(self) -> np.ndarray:
        return self.index.ordinals

    def _batches(self) -> Iterator[Descriptors]:
        assert self.spec is not None
        reader = open_reader(self.path)
        try:
            chunk = _chunk_size(self.count, self.batch_size, self.workers)
            work = describe_partial(self.spec, reader, self.path, self.index.image_topic,
                                    self.thumbnails is not None)
            results = ordered_map(work, iter_image_messages(self.path, reader, self.index, chunk),
                                  self.workers, "thread")
            if self.thumbnails is not None:
                self.thumbnails.clear()
            sink = self.thumbnails if self.thumbnails is not None else []
            yield from _rebatch(_keep_thumbnails(results, sink), self.batch_size,
                                lambda i: f"{self.path}: frame {i} of "
                                          f"{self.index.image_topic}")
        finally:
            reader.close()


class NpySource(FrameSource):
    """Precomputed descriptors: a 2-D float ``.npy`` array, one row per frame.

    The file is memory-mapped and validated in full when opened (one sequential pass, about
    1 GB/s from the page cache) so that a NaN in the last row fails before anything is ingested.
    float64/float16 are converted to float32 batch by batch.
    """

    kind = "npy"

    def __init__(self, path: Path, spec: DescriptorSpec | None, options: _Options) -> None:
        if options.thumbnails:
            raise InputError(f"{path}: a .npy holds descriptors, not images: thumbnails need "
                             "an image folder or a video")
        array = _load_npy(path)
        if spec is not None and array.shape[1] != spec.dim:
            raise DescriptorShapeError(
                f"{path}: descriptors have {array.shape[1]} dimensions, {spec} has {spec.dim}"
            )
        super().__init__(path, None, int(array.shape[1]), options)
        self.array = array[:: self.stride]
        self._source_frames = int(array.shape[0])

    @property
    def count(self) -> int:
        return int(self.array.shape[0])

    @property
    def source_frames(self) -> int:
        return self._source_frames

    def _batches(self) -> Iterator[Descriptors]:
        for start in range(0, self.count, self.batch_size):
            yield np.ascontiguousarray(
                self.array[start : start + self.batch_size], dtype=np.float32
            )


def _load_npy(path: Path) -> DescriptorsLike:
    try:
        array = np.load(path, mmap_mode="r", allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise InputError(f"{path}: cannot read .npy file ({exc})") from exc
    if not isinstance(array, np.ndarray):  # np.load returns an NpzFile for a .npz renamed .npy
        raise InputError(f"{path}: not a .npy array file")
    if array.ndim != 2:
        raise DescriptorShapeError(
            f"{path}: expected a 2-D (frames x dims) array, got shape {array.shape}"
        )
    if not np.issubdtype(array.dtype, np.floating):
        raise DescriptorShapeError(f"{path}: expected float descriptors, got dtype {array.dtype}")
    if array.shape[0] == 0:
        raise EmptySequenceError(f"{path}: no descriptors (shape {array.shape})")
    if array.shape[1] == 0:
        raise InputError(f"{path}: no descriptors (shape {array.shape})")
    rows = max(1, (64 << 20) // max(1, array.shape[1] * array.dtype.itemsize))
    for start in range(0, array.shape[0], rows):
        problem = descriptor_problem(array[start : start + rows])
        if problem is not None:
            row, why = problem
            kind = ("contains NaN or Inf" if not np.isfinite(array[start + row]).all()
                    else "is out of range")
            raise InvalidDescriptorError(f"{path}: row {start + row} {kind} ({why})")
    return array


def open_source(
    path: str | Path,
    spec: DescriptorSpec | None = None,
    stride: int = 1,
    batch_size: int = 256,
    workers: int | None = None,
    executor: str = "thread",
    progress: ProgressCallback | None = None,
    thumbnails: bool = False,
    bag: BagOptions | None = None,
) -> FrameSource:
    """Open a directory of images, a video file, a ``.npy`` of descriptors or a bag.

    - ``path``: a directory (its image files in natural order; other files ignored), a video
      (``.mp4 .avi .mov .mkv .m4v .mpg .mpeg .webm``), a ``.npy`` of shape (frames, dims) or
      a ROS bag (``.bag``, ``.mcap``, ``.db3`` or a ROS 2 bag folder; the ``[ros]`` extra).
    - ``spec``: the descriptor of images and video (default ``DescriptorSpec("hog")``, the
      paper's); for a ``.npy`` only checked against the file's dimension.
    - ``stride``: keep frames 0, stride, 2*stride, ...; ``batch_size``: rows per batch of
      :meth:`FrameSource.iter_batches`.
    - ``workers``: decode/describe workers (default: the cores available to this process);
      ``executor``: ``"thread"`` (default: OpenCV releases the GIL, threads start instantly) or
      ``"process"``, for image directories (a video always uses threads).
    - ``progress``: ``progress(frames_done, total_or_None)`` after each batch.
    - ``thumbnails``: also make a small JPEG of each frame (:attr:`FrameSource.thumbnails`;
      images and video only; each image file is then decoded a second time, in colour).
    - ``bag``: a bag's image and GNSS topics and ``every_m`` (:mod:`sprint_map.frontend.bags`);
      refused for any other source.

    Raises :class:`InputError` (missing path, a directory without images, an unsupported file
    type, a video that cannot be opened or has no frame, an unreadable ``.npy``, thumbnails
    asked of a ``.npy``), :class:`DescriptorShapeError` (a ``.npy`` not 2-D float or not of
    ``spec.dim``), :class:`InvalidDescriptorError` (a ``.npy`` with NaN or Inf). O(1): frames
    are read by :meth:`FrameSource.iter_batches`.
    """
    path = Path(path)
    for name, value in (("stride", stride), ("batch_size", batch_size)):
        if not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive integer")
    if workers is None:
        workers = default_workers()
    if workers < 1:
        raise ValueError("workers must be >= 1")
    if executor not in EXECUTORS:
        raise ValueError(f"executor must be one of {', '.join(EXECUTORS)}")
    if not path.exists():
        raise InputError(f"{path}: no such file or directory")
    options = _Options(stride, batch_size, workers, executor, progress, thumbnails)
    if is_bag(path):
        return BagSource(path, spec or DescriptorSpec("hog"), options, bag or BagOptions())
    if bag is not None and bag != BagOptions():
        raise InputError(f"{path}: --image-topic, --gnss-topic and --every-m are for ROS bags "
                         "(.bag, .mcap, a ROS 2 bag folder)")
    if path.is_dir():
        return ImageDirSource(path, spec or DescriptorSpec("hog"), options)
    if path.suffix.lower() == ".npy":
        return NpySource(path, spec, options)
    if is_video_name(path.name):
        return VideoSource(path, spec or DescriptorSpec("hog"), options)
    raise InputError(
        f"{path}: unsupported source (expected an image directory, a video file, a .npy or a "
        "ROS bag)"
    )


#: A drive folder's own positions, used without ``--positions`` (see :func:`own_positions`).
POSITIONS_FILE = "positions.csv"


def own_positions(path: str | Path) -> Path | None:
    """The ``positions.csv`` a drive carries: inside a drive folder (images, a ROS 2 bag), or
    beside a file that is the only drive source of its folder (``run-4/descriptors.npy``,
    ``mon/drive.bag``); None otherwise. O(files in the folder)."""
    path = Path(path)
    if path.is_dir():
        inside = path / POSITIONS_FILE
        return inside if inside.is_file() else None
    beside = path.parent / POSITIONS_FILE
    if not beside.is_file():
        return None
    sources = [p for p in path.parent.iterdir() if not p.name.startswith(".") and p.is_file()
               and (p.suffix.lower() == ".npy" or is_video_name(p.name) or is_bag(p))]
    return beside if sources == [path] or [s.resolve() for s in sources] == [path.resolve()] \
        else None


def drive_names(paths: list[Path], names: list[str]) -> list[str]:
    """Sequence names of several drives: each source's own name, or, where two collide
    (``mon/descriptors.npy``, ``tue/descriptors.npy``), the name of the drive's folder.

    Raises
    ------
    InputError
        Two drives would still share a name. O(drives).
    """
    def count(values: list[str]) -> dict[str, int]:
        out: dict[str, int] = {}
        for value in values:
            out[value] = out.get(value, 0) + 1
        return out

    first = count(names)
    out = [name if first[name] == 1 else (path.resolve().parent.name if path.is_file()
                                          or not path.is_dir() else name)
           for path, name in zip(paths, names, strict=True)]
    final = count(out)
    for path, name in zip(paths, out, strict=True):
        if final[name] > 1:
            others = [str(p) for p, n in zip(paths, out, strict=True) if n == name]
            raise InputError(f"{path}: drives {', '.join(others)} would all be named {name!r} "
                             "(by their file and by their folder): ingest them one by one "
                             "with --name")
    return out


def drive_positions(source: FrameSource, path: str | Path, positions: str | Path | None,
                    stride: int) -> Positions | None:
    """A drive's positions: the file ``positions`` if given, else what the source carries (a
    bag's GNSS: ``source.positions``), else the drive's own ``positions.csv``
    (:func:`~sprint_map.frontend.sources.own_positions`), else None. ``source`` is the
    opened :class:`~sprint_map.frontend.sources.FrameSource` of ``path``. O(rows)."""
    if positions is None and source.positions is not None:
        return source.positions
    found = Path(positions) if positions is not None else own_positions(path)
    if found is None:
        return None
    ordinals = source.ordinals
    if ordinals is None:  # a video: its frame count is known only once decoded
        table = read_positions(found, None)
        return table.subset(np.arange(0, len(table), stride))
    return read_positions(found, ordinals, source_frames=source.source_frames)
