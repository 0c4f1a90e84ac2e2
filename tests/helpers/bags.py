"""Small ROS bags written with rosbags' own writers: ROS 1 ``.bag``, ROS 2 (sqlite3 or MCAP)
folders and bare ``.mcap`` files, with an image topic and a NavSatFix topic."""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

KINDS = ("ros1", "ros2-sqlite3", "ros2-mcap", "mcap")


@dataclass
class Fix:
    t_ns: int
    lat: float
    lon: float
    status: int = 0  # NavSatStatus.STATUS_FIX
    sigma: float | None = None


@dataclass
class BagSpec:
    images: Sequence[np.ndarray]  # BGR uint8
    image_ns: Sequence[int]
    fixes: Sequence[Fix] = ()
    compressed: bool = True
    encoding: str = "bgr8"  # raw images: bgr8, rgb8, mono8
    image_topic: str = "/camera/image"
    gnss_topic: str = "/gnss/fix"
    extra_image_topics: tuple[str, ...] = ()
    extra_gnss_topics: tuple[str, ...] = ()
    extra: dict[str, int] = field(default_factory=dict)
    # connections carrying the image / GNSS topic (a topic re-advertised, two recordings):
    # message i goes on connection i % n
    image_connections: int = 1
    gnss_connections: int = 1
    # ROS 2 only: zstd compression "file", "message" or "storage" (MCAP chunks), None: none
    compression: str | None = None


def _typestore(ros1: bool):
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)


def _image_msg(ts, image: np.ndarray, t_ns: int, compressed: bool, encoding: str):
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    stamp = Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9)
    header = (Header(seq=0, stamp=stamp, frame_id="cam")  # ROS 1 headers have a seq
              if "seq" in Header.__dataclass_fields__ else Header(stamp=stamp, frame_id="cam"))
    if compressed:
        ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 90])
        assert ok
        return ts.types["sensor_msgs/msg/CompressedImage"](
            header=header, format="jpeg", data=np.frombuffer(data.tobytes(), dtype=np.uint8))
    if encoding == "mono8":
        pixels = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    elif encoding == "rgb8":
        pixels = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    else:
        pixels = image
    height, width = pixels.shape[:2]
    step = width * (1 if pixels.ndim == 2 else pixels.shape[2])
    return ts.types["sensor_msgs/msg/Image"](
        header=header, height=height, width=width, encoding=encoding, is_bigendian=0,
        step=step, data=np.ascontiguousarray(pixels).reshape(-1))


def _fix_msg(ts, fix: Fix):
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    stamp = Time(sec=fix.t_ns // 10**9, nanosec=fix.t_ns % 10**9)
    header = (Header(seq=0, stamp=stamp, frame_id="gps")
              if "seq" in Header.__dataclass_fields__ else Header(stamp=stamp, frame_id="gps"))
    Status = ts.types["sensor_msgs/msg/NavSatStatus"]
    cov = np.zeros(9)
    kind = 0
    if fix.sigma is not None:
        cov[0] = cov[4] = fix.sigma**2
        cov[8] = (2 * fix.sigma) ** 2
        kind = 2
    return ts.types["sensor_msgs/msg/NavSatFix"](
        header=header, status=Status(status=fix.status, service=1), latitude=fix.lat,
        longitude=fix.lon, altitude=10.0, position_covariance=cov,
        position_covariance_type=kind)


def _qos(n: int) -> list:
    """QoS profiles of a topic's ``n``-th connection (none for the first): a ROS 2 bag holds
    two connections of one topic when they were offered with different profiles."""
    if not n:
        return []
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    never = QosTime(sec=0, nsec=0)
    return [Qos(QosHistory.KEEP_LAST, n, QosReliability.RELIABLE, QosDurability.VOLATILE,
                never, never, QosLiveliness.AUTOMATIC, never, False)]


def write_bag(path: Path, kind: str, spec: BagSpec) -> Path:
    """Write ``spec`` as a bag of ``kind``; returns what to give ``ingest`` (a file or a
    folder)."""
    ros1 = kind == "ros1"
    ts = _typestore(ros1)
    image_type = ("sensor_msgs/msg/CompressedImage" if spec.compressed
                  else "sensor_msgs/msg/Image")
    fix_type = "sensor_msgs/msg/NavSatFix"
    records = []  # (t, topic, msgtype, connection number, msg)
    for i, (image, t) in enumerate(zip(spec.images, spec.image_ns, strict=True)):
        msg = _image_msg(ts, image, t, spec.compressed, spec.encoding)
        records.append((t, spec.image_topic, image_type, i % spec.image_connections, msg))
        for topic in spec.extra_image_topics:
            records.append((t, topic, image_type, 0, msg))
    for i, fix in enumerate(spec.fixes):
        msg = _fix_msg(ts, fix)
        records.append((fix.t_ns, spec.gnss_topic, fix_type, i % spec.gnss_connections, msg))
        for topic in spec.extra_gnss_topics:
            records.append((fix.t_ns, topic, fix_type, 0, msg))
    records.sort(key=lambda r: r[0])
    connections = sorted({(r[1], r[2], r[3]) for r in records})
    if ros1:
        from rosbags.rosbag1 import Writer

        path = path.with_suffix(".bag")
        with Writer(path) as writer:
            conns = {(topic, n): writer.add_connection(topic, msgtype, typestore=ts,
                                                       callerid=f"/node{n}")
                     for topic, msgtype, n in connections}
            for t, topic, msgtype, n, msg in records:
                writer.write(conns[topic, n], t, ts.serialize_ros1(msg, msgtype))
        return path
    from rosbags.rosbag2 import StoragePlugin, Writer

    plugin = StoragePlugin.SQLITE3 if kind == "ros2-sqlite3" else StoragePlugin.MCAP
    folder = path if kind != "mcap" else path.with_name(path.name + "-dir")
    writer = Writer(folder, version=9, storage_plugin=plugin)
    if spec.compression is not None:
        from rosbags.rosbag2.enums import CompressionFormat, CompressionMode

        writer.set_compression(CompressionMode[spec.compression.upper()],
                               CompressionFormat.ZSTD)
    with writer:
        conns = {(topic, n): writer.add_connection(topic, msgtype, typestore=ts,
                                                   offered_qos_profiles=_qos(n))
                 for topic, msgtype, n in connections}
        for t, topic, msgtype, n, msg in records:
            writer.write(conns[topic, n], t, ts.serialize_cdr(msg, msgtype))
    if kind != "mcap":
        return folder
    (found,) = folder.glob("*.mcap*")
    target = path.with_suffix(".mcap")
    shutil.move(found, target)
    shutil.rmtree(folder)
    return target


def drive_spec(n: int = 12, *, seed: int = 0, hz: float = 5.0, gnss_hz: float = 10.0,
               lat0: float = 59.91, lon0: float = 10.75, speed_mps: float = 10.0,
               size: tuple[int, int] = (48, 64), **kwargs) -> BagSpec:
    """``n`` random textured frames at ``hz``, driving north at ``speed_mps`` with fixes at
    ``gnss_hz`` covering the drive (plus one before and after)."""
    rng = np.random.default_rng(seed)
    images = [cv2.resize(rng.integers(0, 256, (size[0] // 4, size[1] // 4, 3), dtype=np.uint8),
                         (size[1], size[0]), interpolation=cv2.INTER_NEAREST) for _ in range(n)]
    t0 = 1_700_000_000 * 10**9
    image_ns = [t0 + int(i * 1e9 / hz) for i in range(n)]
    duration = (n - 1) / hz
    m = int(duration * gnss_hz) + 3
    fixes = [Fix(t0 + int((j - 1) * 1e9 / gnss_hz),
                 lat0 + speed_mps * ((j - 1) / gnss_hz) / 111_320.0, lon0, sigma=1.5)
             for j in range(m)]
    return BagSpec(images, image_ns, fixes, **kwargs)
