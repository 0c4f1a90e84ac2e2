"""ROS 1 bags, ROS 2 bags (sqlite3 or MCAP) and bare ``.mcap`` files as frame sources.

Read with the pure-Python ``rosbags`` package (the ``[ros]`` extra; no ROS install), imported
only when a bag is opened. A bag is read in two passes:

1. **Index pass**: the image topic's message times (a ROS 1 bag's index holds them; a ROS 2 bag
   or MCAP is read for them, without decoding an image) and every ``sensor_msgs/NavSatFix`` of
   the GNSS topic. Each frame's position is the point of the geodesic between the two valid
   fixes around it at the fraction of the time between them that the frame's time lies at
   (:func:`sprint_map.util.geo.geodesic_points`: across the antimeridian and the poles as
   anywhere else; the accuracy is interpolated linearly); a frame before the first or
   after the last valid fix, or whose neighbouring fixes have an invalid one (``status <
   STATUS_FIX`` or a NaN) between them, has no fix (NaN). The fix's accuracy ``sigma_m`` is
   ``sqrt((var_east + var_north) / 2)`` of its covariance when that is known. The frames kept
   are every ``stride``-th image, then (``every_m``) the first with a fix and each one at
   least ``every_m`` metres (UTM, the first fix's zone) from the last kept (frames without a
   fix are then dropped).
2. **Frame pass**: the kept images, streamed: deserialised, decoded (``sensor_msgs/Image`` in
   ``mono8 mono16 8UC1 16UC1 8UC3 rgb8 bgr8 rgba8 bgra8``, or a ``CompressedImage``) and
   described by parallel worker threads, in order.

Times are the bag's record (log) times of the messages, for images and fixes alike, so both
share one clock whatever the sensors' header stamps say. Memory: the index pass keeps 8 bytes
per image and one small tuple per fix; the frame pass holds a few chunks of images per worker:
flat in the bag's length. Any read error is an :class:`~sprint_map.errors.InputError` naming the
bag; a bag corrupt or truncated in its image data is found by the index pass of a ROS 2 bag or
MCAP, and by the frame pass of a ROS 1 bag (whose index is read, not its data).
"""

from __future__ import annotations

import functools
import heapq
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sprint_map.errors import InputError
from sprint_map.frontend.bagfiles import INSTALL_HINT, BagReadError, open_reader, reading
from sprint_map.frontend.positions import Positions
from sprint_map.util.arrays import Descriptors, Image
from sprint_map.util.geo import GeoFrame, geodesic_points

if TYPE_CHECKING:
    from sprint_map.frontend.descriptors import DescriptorSpec

__all__ = ["BAG_SUFFIXES", "INSTALL_HINT", "BagOptions", "BagReadError", "bag_index",
           "decode_ros_image", "is_bag", "open_reader", "rosbags_available"]

BAG_SUFFIXES = (".bag", ".mcap", ".db3")
IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
GNSS_TYPE = "sensor_msgs/msg/NavSatFix"
_STATUS_FIX = 0  # sensor_msgs/NavSatStatus: -1 no fix, 0 fix, 1 SBAS, 2 GBAS
_COVARIANCE_UNKNOWN = 0


@dataclass(frozen=True)
class BagOptions:
    """Which topics of a bag, and the distance subsampling (``--every-m``)."""

    image_topic: str | None = None
    gnss_topic: str | None = None
    every_m: float | None = None

    def __post_init__(self) -> None:
        if self.every_m is not None and not self.every_m > 0:
            raise InputError(f"--every-m must be > 0 metres, got {self.every_m}")


def rosbags_available() -> bool:
    """Whether the ``rosbags`` package (the ``[ros]`` extra) is installed. O(1)."""
    import importlib.util

    return importlib.util.find_spec("rosbags") is not None


def is_bag(path: Path) -> bool:
    """A ``.bag``, ``.mcap`` or ``.db3`` file, or a ROS 2 bag folder (``metadata.yaml``)."""
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix.lower() in BAG_SUFFIXES


@dataclass
class BagIndex:
    """What the index pass found: the kept frames' message times and positions."""

    image_topic: str
    gnss_topic: str | None
    times_ns: np.ndarray  # (n,) int64 record times of the kept image messages
    ordinals: np.ndarray  # (n,) int64 their ordinal among the topic's messages
    positions: Positions | None  # geographic, one row per kept frame
    image_count: int = 0  # messages of the image topic (every connection), before any selection
    warnings: tuple[str, ...] = ()  # what the user should know (fixes dropped, ...)


def _pick(path: Path, reader: Any, wanted: str | None, types: tuple[str, ...], what: str,
          option: str, required: bool) -> tuple[str, list[Any]] | None:
    """Topic ``wanted``, or the only topic of one of ``types``, with every connection that
    carries it (a topic re-advertised, or two recordings, has several), or None."""
    topics: dict[str, set[str]] = {}
    for conn in reader.connections:
        topics.setdefault(conn.topic, set()).add(conn.msgtype)
    if wanted is None:
        candidates = sorted(t for t, m in topics.items() if m & set(types))
        if not candidates:
            if not required:
                return None
            raise InputError(f"{path}: no {what} topic ({' or '.join(types)}) in the bag")
        if len(candidates) > 1:
            raise InputError(f"{path}: several {what} topics ({', '.join(candidates)}): choose "
                             f"one with {option}")
        wanted = candidates[0]
    if wanted not in topics:
        listing = ", ".join(f"{t} ({' and '.join(sorted(m))})"
                            for t, m in sorted(topics.items())) or "none"
        raise InputError(f"{path}: no topic {wanted!r} in the bag (topics: {listing})")
    if topics[wanted] - set(types):
        raise InputError(f"{path}: topic {wanted!r} is {' and '.join(sorted(topics[wanted]))}, "
                         f"not {' or '.join(types)}")
    return wanted, [c for c in reader.connections if c.topic == wanted]


def _image_times(reader: Any, connections: list[Any]) -> np.ndarray:
    """Record times (ns) of the messages of ``connections`` (one topic), in the order the
    frame pass reads them (time order, every connection): from a ROS 1 bag's index, else by
    reading the topic (its data is not decoded). O(messages)."""
    if not reader.is2:
        entries = heapq.merge(*(c.owner.indexes[c.id] for c in connections))
        return np.fromiter((entry.time for entry in entries), dtype=np.int64)
    return np.fromiter((t for _, t, _ in reader.messages(connections=connections)),
                       dtype=np.int64)


@dataclass(frozen=True)
class _Fixes:
    """Every NavSatFix of the GNSS topic, in time order."""

    times: np.ndarray  # (m,) int64 record times
    latlon: np.ndarray  # (m, 2)
    sigma: np.ndarray  # (m,) metres, NaN: unknown
    valid: np.ndarray  # (m,) bool
    unbounded: int  # fixes dropped for a covariance that is not finite


def _fixes(reader: Any, connections: list[Any]) -> _Fixes:
    """The fixes of ``connections`` (one topic, every connection). A fix with ``status <
    STATUS_FIX``, a coordinate not finite or out of range, or a known covariance whose
    horizontal variance is not finite (a receiver saying it does not know where it is) is
    not valid; a known variance <= 0 leaves the accuracy unknown. O(m)."""
    times, latlon, sigma, valid = [], [], [], []
    unbounded = 0
    for conn, t, raw in reader.messages(connections=connections):
        msg = reader.deserialize(raw, conn.msgtype)
        lat, lon = float(msg.latitude), float(msg.longitude)
        ok = (int(msg.status.status) >= _STATUS_FIX and math.isfinite(lat)
              and math.isfinite(lon) and -90 <= lat <= 90 and -180 <= lon <= 180)
        cov = np.asarray(msg.position_covariance, dtype=np.float64)
        known = int(msg.position_covariance_type) != _COVARIANCE_UNKNOWN and len(cov) == 9
        var = float(cov[0] + cov[4]) if known else math.nan
        if known and not math.isfinite(var):
            unbounded += ok
            ok = False
        times.append(t)
        latlon.append((lat, lon))
        sigma.append(math.sqrt(var / 2) if math.isfinite(var) and var > 0 else math.nan)
        valid.append(ok)
    order = np.argsort(np.asarray(times, dtype=np.int64), kind="stable")
    return _Fixes(np.asarray(times, dtype=np.int64)[order],
                  np.asarray(latlon, dtype=np.float64).reshape(-1, 2)[order],
                  np.asarray(sigma, dtype=np.float64)[order],
                  np.asarray(valid, dtype=bool)[order], unbounded)


def interpolate_fixes(frame_ns: np.ndarray, fix_ns: np.ndarray, latlon: np.ndarray,
                      sigma: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(n, 2)`` lat/lon and ``(n,)`` sigma of each frame time, interpolated between the
    valid fixes around it (NaN outside them or across an invalid fix; see the module
    docstring). O((n + m) log m)."""
    n = len(frame_ns)
    out, out_sigma = np.full((n, 2), np.nan), np.full(n, np.nan)
    if not len(fix_ns):
        return out, out_sigma
    after = np.searchsorted(fix_ns, frame_ns, side="left")  # first fix at or after the frame
    exact = (after < len(fix_ns)) & (fix_ns[np.minimum(after, len(fix_ns) - 1)] == frame_ns)
    hi = np.minimum(after, len(fix_ns) - 1)
    lo = np.where(exact, hi, after - 1)
    inside = (after < len(fix_ns)) & (lo >= 0)
    lo_c = np.maximum(lo, 0)
    usable = inside & valid[lo_c] & valid[hi]
    span = (fix_ns[hi] - fix_ns[lo_c]).astype(np.float64)
    w = np.where(span > 0, (frame_ns - fix_ns[lo_c]) / np.where(span > 0, span, 1.0), 0.0)
    out[usable] = geodesic_points(latlon[lo_c[usable]], latlon[hi[usable]], w[usable])
    s = np.where(np.isnan(sigma[lo_c]) | np.isnan(sigma[hi]), np.nan,
                 sigma[lo_c] * (1 - w) + sigma[hi] * w)
    out_sigma[usable] = s[usable]
    return out, out_sigma


def _every_m(latlon: np.ndarray, every_m: float) -> np.ndarray:
    """Indices of the frames kept by distance: the first with a fix, then each at least
    ``every_m`` metres from the last kept. O(n)."""
    fixed = np.flatnonzero(np.isfinite(latlon).all(axis=1))
    if not len(fixed):
        return fixed
    frame = GeoFrame.for_fix(*latlon[fixed[0]])
    xy = frame.project(latlon[fixed, 0], latlon[fixed, 1])
    keep = [0]
    last = xy[0]
    for i in range(1, len(fixed)):
        if math.hypot(xy[i, 0] - last[0], xy[i, 1] - last[1]) >= every_m:
            keep.append(i)
            last = xy[i]
    return fixed[keep]


def bag_index(path: Path, reader: Any, options: BagOptions, stride: int) -> BagIndex:
    """The index pass (see the module docstring). O(images + fixes).

    Raises
    ------
    InputError
        No (or several) image topic, a named topic missing or of another type, no image
        message, ``--every-m`` without a GNSS topic, or a bag that cannot be read.
    """
    with reading(path):
        image = _pick(path, reader, options.image_topic, IMAGE_TYPES, "image",
                      "--image-topic", required=True)
        gnss = _pick(path, reader, options.gnss_topic, (GNSS_TYPE,), "GNSS", "--gnss-topic",
                     required=options.gnss_topic is not None or options.every_m is not None)
    assert image is not None
    image_topic, gnss_topic = image[0], None if gnss is None else gnss[0]
    with reading(path, image_topic):
        times = _image_times(reader, image[1])
    if np.any(np.diff(times) < 0):
        raise BagReadError(f"{path}: topic {image_topic!r}: the bag's index lists its messages "
                           "out of time order (a damaged index)")
    fixes = None
    if gnss is not None:
        with reading(path, gnss_topic):
            fixes = _fixes(reader, gnss[1])
    if not len(times):
        raise InputError(f"{path}: no message on image topic {image_topic!r}")
    ordinals = np.arange(0, len(times), stride, dtype=np.int64)
    kept = times[ordinals]
    positions = None
    warnings = []
    if fixes is not None:
        if fixes.unbounded:
            warnings.append(f"{path}: topic {gnss_topic!r}: {fixes.unbounded} of "
                            f"{len(fixes.times)} fixes report a covariance that is not finite "
                            "and were not used (frames near them have no fix)")
        latlon, sigma = interpolate_fixes(kept, fixes.times, fixes.latlon, fixes.sigma,
                                          fixes.valid)
        if options.every_m is not None:
            keep = _every_m(latlon, options.every_m)
            if not len(keep):
                raise InputError(f"{path}: --every-m needs fixes, and no image of "
                                 f"{image_topic!r} has one on {gnss_topic!r}")
            ordinals, kept, latlon, sigma = ordinals[keep], kept[keep], latlon[keep], sigma[keep]
        positions = Positions(ordinals, latlon, None,
                              sigma if np.isfinite(sigma).any() else None,
                              kept.astype(np.float64) / 1e9, geographic=True)
    return BagIndex(image_topic, gnss_topic, kept, ordinals, positions, len(times),
                    tuple(warnings))


def decode_ros_image(msg: Any, msgtype: str, label: str, grayscale: bool) -> Image:
    """The image of a deserialised ``sensor_msgs/Image`` or ``CompressedImage`` (gray, or BGR
    when not ``grayscale``), as OpenCV holds it.

    Raises
    ------
    InputError
        An unsupported encoding, or data that do not match the declared size.
    """
    import cv2

    if msgtype.endswith("CompressedImage"):
        from sprint_map.frontend.imagefiles import decode_image

        return decode_image(bytes(msg.data), label, grayscale=grayscale)
    encoding = str(msg.encoding).lower()
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    channels = {"mono8": 1, "8uc1": 1, "mono16": 1, "16uc1": 1, "8uc3": 3, "rgb8": 3,
                "bgr8": 3, "rgba8": 4, "bgra8": 4}.get(encoding)
    if channels is None:
        raise InputError(f"{label}: unsupported image encoding {msg.encoding!r} (mono8, mono16, "
                         "rgb8, bgr8, rgba8, bgra8 or a CompressedImage)")
    depth = 2 if "16" in encoding else 1
    data = np.asarray(msg.data, dtype=np.uint8)
    if height < 1 or width < 1 or step < width * channels * depth or len(data) < step * height:
        raise InputError(f"{label}: image data of {len(data)} bytes do not fit {width}x{height} "
                         f"{msg.encoding} (step {step})")
    rows = data[: step * height].reshape(height, step)[:, : width * channels * depth]
    if depth == 2:
        big = bool(msg.is_bigendian)
        rows = rows.copy().view(">u2" if big else "<u2").astype(np.uint16)
        image: Image = (rows >> 8).astype(np.uint8).reshape(height, width, channels)
    else:
        image = rows.reshape(height, width, channels)
    if channels == 1:
        image = image[:, :, 0]
        return np.ascontiguousarray(image) if grayscale else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    code = {"rgb8": (cv2.COLOR_RGB2GRAY, cv2.COLOR_RGB2BGR),
            "rgba8": (cv2.COLOR_RGBA2GRAY, cv2.COLOR_RGBA2BGR),
            "bgra8": (cv2.COLOR_BGRA2GRAY, cv2.COLOR_BGRA2BGR),
            "bgr8": (cv2.COLOR_BGR2GRAY, None), "8uc3": (cv2.COLOR_BGR2GRAY, None)}[encoding]
    image = np.ascontiguousarray(image)
    if grayscale:
        return cv2.cvtColor(image, code[0])
    return image if code[1] is None else cv2.cvtColor(image, code[1])


def describe_messages(spec: DescriptorSpec, deserialize: Any, path: Path, topic: str,
                      thumbnails: bool, chunk: list[tuple[int, str, bytes]]
                      ) -> tuple[Descriptors, list[bytes]]:
    """Deserialise, decode and describe a chunk of ``(ordinal, msgtype, raw)`` image messages
    (runs in a worker thread); their thumbnails too when asked. O(chunk pixels)."""
    from sprint_map.frontend.thumbnails import make_thumbnail

    images = []
    for ordinal, msgtype, raw in chunk:
        with reading(path, topic, ordinal):
            msg = deserialize(raw, msgtype)
            images.append(decode_ros_image(msg, msgtype, f"{path}: topic {topic!r}: image "
                                           f"message {ordinal}", grayscale=spec.grayscale))
    rows = spec.describe_batch(images)
    return rows, [make_thumbnail(image) for image in images] if thumbnails else []


def iter_image_messages(path: Path, reader: Any, index: BagIndex, chunk: int
                        ) -> Iterator[list[tuple[int, str, bytes]]]:
    """The kept image messages as chunks of ``(ordinal, msgtype, raw)``, in order: the
    messages of every connection of the image topic, in the time order the index pass
    numbered them (a message whose time is not the one the index pass found there is an
    error: the bag changed, or its index and its data disagree). O(bag)."""
    connections = [c for c in reader.connections if c.topic == index.image_topic]
    where = dict(zip(index.ordinals.tolist(), index.times_ns.tolist(), strict=True))
    out: list[tuple[int, str, bytes]] = []
    ordinal = 0
    with reading(path, index.image_topic):
        for conn, t, raw in reader.messages(connections=connections):
            expected = where.get(ordinal)
            if expected is not None:
                if int(t) != expected:
                    raise BagReadError(
                        f"{path}: topic {index.image_topic!r}: image message {ordinal} is at "
                        f"{int(t)} ns, its index said {expected} ns (the bag changed while "
                        "read, or its index and data disagree)")
                out.append((ordinal, conn.msgtype, bytes(raw)))
                if len(out) == chunk:
                    yield out
                    out = []
            ordinal += 1
    if out:
        yield out
    if ordinal <= int(index.ordinals[-1]):
        raise BagReadError(f"{path}: topic {index.image_topic!r}: the bag ended after "
                           f"{ordinal} of the images its index lists (truncated?)")


def describe_partial(spec: DescriptorSpec, reader: Any, path: Path, topic: str,
                     thumbnails: bool) -> Any:
    """The worker function of the frame pass (see :func:`describe_messages`)."""
    return functools.partial(describe_messages, spec, reader.deserialize, path, topic,
                             thumbnails)
