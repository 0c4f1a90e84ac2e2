"""Data sets on disk: one folder per traversal, optional positions, optional ``dataset.json``.

Layout::

    my-dataset/
        dataset.json            optional: {"alignment": "frame", "tolerance_frames": 1}
                                       or {"alignment": "position", "radius_m": 10,
                                           "heading_deg": 45}
        summer/                 a traversal: image files (natural order) ...
            positions.csv       ... optional, frame,x,y[,heading_deg] (see positions.py)
        winter/
        drive-3/
            drive-3.mp4         ... or exactly one video file ...
        run-4/
            descriptors.npy     ... or precomputed descriptors (takes precedence)

Traversals are the non-hidden sub-folders, in natural order. Other top-level files (a README)
are ignored. ``dataset.json`` may also hold ``"description"`` and ``"generator"`` entries,
which are kept in :attr:`Dataset.info` but not interpreted, and ``"twins"`` (traversal ->
``[start, stop)`` frame ranges on identical-twin places, :meth:`Dataset.twin_frames`), which
evaluations report separately.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from sprint_map.errors import ConfigError, InputError
from sprint_map.frontend.descriptors import DescriptorSpec
from sprint_map.frontend.groundtruth import GroundTruth, GroundTruthSpec
from sprint_map.frontend.imagefiles import is_image_name, is_video_name, list_images, natural_key
from sprint_map.frontend.positions import Positions, read_positions
from sprint_map.frontend.sources import FrameSource, ProgressCallback, open_source
from sprint_map.util.arrays import Float64Array
from sprint_map.util.geo import GeoFrame

__all__ = ["DATASET_FILE", "DESCRIPTORS_FILE", "Dataset", "POSITIONS_FILE", "Traversal",
           "frame_ranges"]

DATASET_FILE = "dataset.json"
POSITIONS_FILE = "positions.csv"
DESCRIPTORS_FILE = "descriptors.npy"

# dataset.json keys that are metadata, not part of the ground-truth rule.
_INFO_KEYS = ("description", "generator", "twins")


class Traversal:
    """One traversal (sub-folder) of a :class:`Dataset`.

    Attributes
    ----------
    name : str
        The folder name (the default sequence name).
    folder : Path
        The traversal folder.
    kind : str
        ``"images"``, ``"video"`` or ``"npy"``.
    source_path : Path
        What :func:`~sprint_map.frontend.sources.open_source` is given: the folder itself, the
        video file or ``descriptors.npy``.
    positions_path : Path or None
        ``positions.csv`` if present.
    """

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.name = folder.name
        positions = folder / POSITIONS_FILE
        self.positions_path: Path | None = positions if positions.is_file() else None
        self._count: int | None = None
        npy = folder / DESCRIPTORS_FILE
        if npy.is_file():
            self.kind, self.source_path = "npy", npy
            return
        try:
            names = sorted(os.listdir(folder), key=natural_key)
        except OSError as exc:
            raise InputError(f"{folder}: cannot list directory ({exc.strerror or exc})") from exc
        videos = [n for n in names if is_video_name(n) and not n.startswith(".")]
        has_images = any(is_image_name(n) and not n.startswith(".") for n in names)
        if len(videos) > 1 or (videos and has_images):
            raise InputError(
                f"{folder}: ambiguous traversal (holds {'images and ' if has_images else ''}"
                f"{len(videos)} video file(s)); keep one video or only images"
            )
        if videos:
            self.kind, self.source_path = "video", folder / videos[0]
        elif has_images:
            self.kind, self.source_path = "images", folder
            self._count = len(list_images(folder))
        else:
            raise InputError(f"{folder}: traversal holds no images, video or {DESCRIPTORS_FILE}")

    @property
    def count(self) -> int | None:
        """Frames before any stride, if known without decoding (``None`` for a video)."""
        if self._count is None and self.kind == "npy":
            try:
                array = np.load(self.source_path, mmap_mode="r", allow_pickle=False)
            except (OSError, ValueError, EOFError) as exc:
                raise InputError(f"{self.source_path}: cannot read .npy file ({exc})") from exc
            self._count = int(array.shape[0]) if getattr(array, "ndim", 0) >= 1 else 0
        return self._count

    def open(
        self,
        spec: DescriptorSpec | None = None,
        stride: int = 1,
        batch_size: int = 256,
        workers: int | None = None,
        executor: str = "thread",
        progress: ProgressCallback | None = None,
        thumbnails: bool = False,
    ) -> FrameSource:
        """Open the traversal as a frame source named after the folder (see ``open_source``;
        ``thumbnails``: also a small JPEG of each frame, images and video only)."""
        source = open_source(
            self.source_path, spec, stride, batch_size, workers, executor, progress,
            thumbnails=thumbnails,
        )
        source.name = self.name
        return source

    def positions(self, stride: int = 1, frame: GeoFrame | None = None
                  ) -> Float64Array | None:
        """Positions ``frame, x, y[, heading_deg]`` of the frames kept with ``stride`` (NaN
        for a frame without a fix), or ``None`` without ``positions.csv``; latitude/longitude
        are projected into ``frame`` (default: the UTM zone of the first fix).

        For a video, whose frame count is unknown before decoding, the CSV's last frame is
        trusted; for images and descriptors no row may lie beyond the frame count.
        """
        table = self.position_table(stride)
        if table is None:
            return None
        if table.geographic:
            fix = table.first_fix()
            frame = frame or (GeoFrame.for_fix(*fix) if fix else GeoFrame(31))
        return table.metric(frame).table()

    def position_table(self, stride: int = 1) -> Positions | None:
        """The :class:`~sprint_map.frontend.positions.Positions` of ``positions.csv`` for the
        frames kept with ``stride`` (as read: latitude/longitude stay so), or None."""
        if self.positions_path is None:
            return None
        count = self.count
        if count is None:
            table = read_positions(self.positions_path, None)
            return table.subset(np.arange(0, len(table), stride))
        return read_positions(self.positions_path, -(-count // stride), stride)

    def __repr__(self) -> str:
        return f"Traversal({self.name!r}, kind={self.kind!r}, count={self.count})"


class Dataset:
    """A folder of traversals. Open with :meth:`open`.

    Attributes
    ----------
    path : Path
    traversals : list of Traversal
        In natural folder-name order.
    gt_spec : GroundTruthSpec or None
        From ``dataset.json`` merged with the override given to :meth:`open`; ``None`` if
        neither declares an alignment.
    info : dict
        The ``description`` / ``generator`` entries of ``dataset.json``, if any.
    """

    def __init__(
        self,
        path: Path,
        traversals: list[Traversal],
        gt_spec: GroundTruthSpec | None,
        info: dict[str, Any],
    ) -> None:
        self.path = path
        self.traversals = traversals
        self.gt_spec = gt_spec
        self.info = info
        self._by_name = {t.name: t for t in traversals}

    @classmethod
    def open(
        cls, path: str | Path, ground_truth: GroundTruthSpec | Mapping[str, Any] | None = None
    ) -> Dataset:
        """Open a data-set folder.

        Parameters
        ----------
        path : str or Path
            The data-set folder.
        ground_truth : GroundTruthSpec or mapping, optional
            Overrides ``dataset.json`` key by key, e.g. ``{"alignment": "frame",
            "tolerance_frames": 1}`` for a read-only folder without one (Nordland).

        Raises
        ------
        InputError
            Missing folder, no traversal folder, an unusable traversal folder, or an invalid
            ``dataset.json`` (named in the message).
        ConfigError
            An invalid override.
        """
        path = Path(path)
        if not path.is_dir():
            raise InputError(f"{path}: no such data-set directory")
        declared, info = _read_dataset_json(path / DATASET_FILE)
        if isinstance(ground_truth, GroundTruthSpec):
            override: dict[str, Any] = ground_truth.to_dict()
        else:
            override = dict(ground_truth or {})
        merged = {**declared, **override}
        gt_spec = None
        if merged:
            if "alignment" not in merged:
                raise ConfigError("ground truth: no alignment given ('frame' or 'position')")
            gt_spec = GroundTruthSpec.from_dict(merged)
        folders = sorted(
            (p for p in path.iterdir() if p.is_dir() and not p.name.startswith(".")),
            key=lambda p: natural_key(p.name),
        )
        if not folders:
            raise InputError(f"{path}: data set has no traversal folders")
        return cls(path, [Traversal(folder) for folder in folders], gt_spec, info)

    def geo_frame(self) -> GeoFrame | None:
        """The UTM zone of the first fix of the first traversal whose ``positions.csv`` holds
        latitude/longitude (all traversals are projected into it), or None. O(CSV rows).

        Raises
        ------
        InputError
            Some traversals' positions are latitude/longitude and others planar ``x, y``: a
            data set has one frame (distances across the two would mean nothing).
        """
        if not hasattr(self, "_geo_frame"):
            frame: GeoFrame | None = None
            kinds: dict[bool, str] = {}
            for traversal in self.traversals:
                table = traversal.position_table()
                if table is None:
                    continue
                kinds.setdefault(table.geographic, traversal.name)
                fix = table.first_fix() if table.geographic else None
                if fix is not None and frame is None:
                    frame = GeoFrame.for_fix(*fix)
            if len(kinds) > 1:
                raise InputError(f"{self.path}: traversal {kinds[True]!r} has latitude/longitude "
                                 f"positions and {kinds[False]!r} planar x, y: a data set keeps "
                                 "one frame")
            self._geo_frame = frame
        return self._geo_frame

    @property
    def names(self) -> list[str]:
        """Traversal names, in order."""
        return [t.name for t in self.traversals]

    def __getitem__(self, name: str) -> Traversal:
        try:
            return self._by_name[name]
        except KeyError:
            raise InputError(
                f"{self.path}: no traversal {name!r} (has {', '.join(self.names)})"
            ) from None

    def __iter__(self) -> Iterator[Traversal]:
        return iter(self.traversals)

    def __len__(self) -> int:
        return len(self.traversals)

    def ground_truth(self, stride: int = 1) -> GroundTruth:
        """Ground truth over this data set's traversals, for frames ingested with ``stride``.

        Positions are read lazily, the first time a traversal is asked about.

        Raises
        ------
        InputError
            If no alignment is declared, or (later, on use) a traversal lacks positions needed
            by position alignment.
        """
        if self.gt_spec is None:
            raise InputError(
                f"{self.path}: no ground truth declared; add {DATASET_FILE} or pass an alignment"
            )
        if self.gt_spec.alignment == "frame":
            lengths = {
                t.name: None if t.count is None else -(-t.count // stride) for t in self.traversals
            }
            return GroundTruth(self.gt_spec, lengths=lengths, stride=stride)
        return GroundTruth(self.gt_spec, positions=_LazyPositions(self, stride), stride=stride)

    def twin_frames(self, name: str, stride: int = 1) -> np.ndarray | None:
        """Which frames of traversal ``name`` (kept with ``stride``) lie on an identical twin,
        by ``dataset.json``'s ``twins`` (traversal -> ``[start, stop)`` frame ranges); None
        when it declares no twins. O(frames).

        Raises
        ------
        InputError
            If ``twins`` is malformed or the traversal's frame count is unknown (a video).
        """
        declared = self.info.get("twins")
        if declared is None:
            return None
        count = self[name].count
        if not isinstance(declared, dict) or count is None:
            raise InputError(f"{self.path / DATASET_FILE}: 'twins' must map traversals to "
                             "frame ranges of image or .npy traversals")
        mask = np.zeros(count, dtype=bool)
        try:
            for start, stop in declared.get(name, []):
                mask[int(start):int(stop)] = True
        except (TypeError, ValueError) as exc:
            raise InputError(f"{self.path / DATASET_FILE}: 'twins' of {name!r}: expected "
                             f"[start, stop) pairs ({exc})") from exc
        return mask[::stride]

    def __repr__(self) -> str:
        return f"Dataset({str(self.path)!r}, traversals={self.names}, ground_truth={self.gt_spec})"


class _LazyPositions(Mapping[str, Float64Array]):
    """Traversal name -> positions array, read from CSV on first access."""

    def __init__(self, dataset: Dataset, stride: int) -> None:
        self._dataset = dataset
        self._stride = stride
        self._cache: dict[str, Float64Array] = {}

    def __getitem__(self, name: str) -> Float64Array:
        if name not in self._cache:
            traversal = self._dataset[name]
            rows = traversal.positions(self._stride, self._dataset.geo_frame())
            if rows is None:
                raise InputError(
                    f"{traversal.folder}: no {POSITIONS_FILE}, needed by position alignment"
                )
            self._cache[name] = rows
        return self._cache[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._dataset.names)

    def __len__(self) -> int:
        return len(self._dataset)


def _read_dataset_json(path: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """Return (ground-truth keys, info keys) of ``dataset.json``; empty dicts if absent."""
    if not path.exists():
        return {}, {}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: cannot read data-set description ({exc})") from exc
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a JSON object")
    info = {key: data.pop(key) for key in _INFO_KEYS if key in data}
    try:
        if data:
            GroundTruthSpec.from_dict(data)  # validate now, so the error names this file
    except ConfigError as exc:
        raise InputError(f"{path}: {exc}") from exc
    return data, info


def frame_ranges(mask: np.ndarray) -> list[list[int]]:
    """``[start, stop)`` ranges of the True runs of a boolean mask (the form of ``dataset.json``'s
    ``twins``). O(len(mask))."""
    padded = np.concatenate([[False], np.asarray(mask, dtype=bool), [False]])
    edges = np.flatnonzero(np.diff(padded.astype(np.int8)))
    return [[int(a), int(b)] for a, b in zip(edges[::2], edges[1::2], strict=True)]
