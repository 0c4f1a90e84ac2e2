"""ROS 1 bags, ROS 2 bags (sqlite3, MCAP) and bare MCAP files as sources, written by rosbags'
own writers: frames, GNSS matched by time, topics, --every-m, bad bags."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

pytest.importorskip("rosbags")

from sprint_map.cli.main import main  # noqa: E402
from sprint_map.errors import InputError  # noqa: E402
from sprint_map.frontend.descriptors import DescriptorSpec  # noqa: E402
from sprint_map.frontend.sources import open_source  # noqa: E402
from sprint_map.map import SprintMap  # noqa: E402
from tests.helpers.bags import KINDS, drive_spec, write_bag  # noqa: E402

HOG = DescriptorSpec("hog")


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("encoding", ["jpeg", "bgr8", "rgb8", "mono8"])
def test_frames_are_the_images(tmp_path, kind, encoding):
    spec = drive_spec(7, compressed=encoding == "jpeg", encoding=encoding)
    src = open_source(write_bag(tmp_path / "drive", kind, spec), HOG, batch_size=3)
    assert (src.kind, src.count, src.image_topic, src.gnss_topic) == (
        "bag", 7, "/camera/image", "/gnss/fix")
    got = src.read_all()
    if encoding == "jpeg":
        images = [cv2.imdecode(cv2.imencode(".jpg", im, [cv2.IMWRITE_JPEG_QUALITY, 90])[1],
                               cv2.IMREAD_GRAYSCALE) for im in spec.images]
    else:
        images = [cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) for im in spec.images]
    np.testing.assert_allclose(got, HOG.describe_batch(images), atol=1e-6)


@pytest.mark.parametrize("kind", KINDS)
def test_gnss_is_interpolated_at_each_frame(tmp_path, kind):
    # frames at 5 Hz, fixes at 10 Hz but offset by 37 ms: every frame lies between two fixes
    spec = drive_spec(9, hz=5.0, gnss_hz=10.0, speed_mps=10.0)
    spec.image_ns = [t + 37_000_000 for t in spec.image_ns]
    src = open_source(write_bag(tmp_path / "d", kind, spec), HOG)
    t = (np.asarray(spec.image_ns) - spec.fixes[1].t_ns) / 1e9
    want_lat = 59.91 + 10.0 * t / 111_320.0
    np.testing.assert_allclose(src.positions.xy[:, 0], want_lat, rtol=0, atol=1e-10)
    np.testing.assert_allclose(src.positions.xy[:, 1], 10.75)
    np.testing.assert_allclose(src.positions.sigma_m, 1.5)
    np.testing.assert_allclose(src.positions.time, np.asarray(spec.image_ns) / 1e9)
    assert src.positions.geographic


def test_invalid_fixes_and_frames_outside_the_fixes_are_gaps(tmp_path):
    spec = drive_spec(10, hz=5.0, gnss_hz=10.0)  # frames every 0.2 s, fixes every 0.1 s
    t0 = spec.image_ns[0]
    spec.image_ns = [t + 50_000_000 for t in spec.image_ns]  # frames at 0.05, 0.25, ... 1.85 s
    spec.fixes = [f for f in spec.fixes if f.t_ns >= t0 + 400_000_000]  # fixes from 0.4 s
    next(f for f in spec.fixes if f.t_ns == t0 + 1_100_000_000).status = -1  # no fix at 1.1
    src = open_source(write_bag(tmp_path / "d", "ros1", spec), HOG)
    # 0.05 and 0.25: before the first fix; 1.05: between 1.0 and the invalid 1.1
    assert src.positions.fixed.tolist() == [False, False, True, True, True, False, True, True,
                                            True, True]
    assert np.isnan(src.positions.sigma_m[[0, 1, 5]]).all()


def test_every_m_keeps_a_frame_per_distance(tmp_path):
    spec = drive_spec(20, hz=5.0, speed_mps=10.0)  # 2 m between frames
    src = open_source(write_bag(tmp_path / "d", "ros2-mcap", spec), HOG)
    kept = open_source(write_bag(tmp_path / "e", "ros2-mcap", spec), HOG,
                       bag=_options(every_m=5.0))
    assert kept.positions.frames.tolist() == [0, 3, 6, 9, 12, 15, 18]
    assert kept.count == 7 and len(kept.read_all()) == 7
    north = (kept.positions.xy[:, 0] - 59.91) * 111_320
    assert np.all(np.diff(north) >= 5.0 - 1e-6)
    strided = open_source(write_bag(tmp_path / "f", "ros1", spec), HOG, stride=2,
                          bag=_options(every_m=5.0))  # stride first, then distance
    assert strided.positions.frames.tolist() == [0, 4, 8, 12, 16]
    np.testing.assert_allclose(kept.read_all()[1], src.read_all()[3], atol=1e-6)


def _options(**kwargs):
    from sprint_map.frontend.bags import BagOptions

    return BagOptions(**kwargs)


@pytest.mark.parametrize(("extra", "options", "message"), [
    ({"extra_image_topics": ("/camera2/image",)}, {},
     r"several image topics \(/camera/image, /camera2/image\): choose one with --image-topic"),
    ({}, {"image_topic": "/nope"}, r"no topic '/nope' in the bag \(topics: /camera/image "
                                   r"\(sensor_msgs/msg/CompressedImage\), /gnss/fix"),
    ({}, {"image_topic": "/gnss/fix"}, "topic '/gnss/fix' is sensor_msgs/msg/NavSatFix, not"),
    ({}, {"gnss_topic": "/gps"}, "no topic '/gps' in the bag"),
    ({"extra_gnss_topics": ("/gps2",)}, {}, "several GNSS topics .*choose one with --gnss-topic"),
])
def test_topic_errors(tmp_path, extra, options, message):
    path = write_bag(tmp_path / "d", "ros1", drive_spec(3, **extra))
    with pytest.raises(InputError, match=message):
        open_source(path, HOG, bag=_options(**options))


def test_the_chosen_topic_among_several(tmp_path):
    spec = drive_spec(3, extra_image_topics=("/camera2/image",), extra_gnss_topics=("/gps2",))
    src = open_source(write_bag(tmp_path / "d", "mcap", spec), HOG,
                      bag=_options(image_topic="/camera2/image", gnss_topic="/gps2"))
    assert (src.image_topic, src.gnss_topic, src.count) == ("/camera2/image", "/gps2", 3)


def test_no_gnss_topic_means_no_positions_but_every_m_needs_one(tmp_path):
    spec = drive_spec(3)
    spec.fixes = []
    path = write_bag(tmp_path / "d", "ros1", spec)
    assert open_source(path, HOG).positions is None
    with pytest.raises(InputError, match="no GNSS topic"):
        open_source(path, HOG, bag=_options(every_m=2.0))


@pytest.mark.parametrize("damage", ["garbage-bag", "truncated-bag", "truncated-mcap",
                                    "garbage-mcap", "no-metadata"])
def test_corrupt_bags_are_one_line_errors(tmp_path, damage):
    kind = "mcap" if "mcap" in damage else "ros1"
    path = write_bag(tmp_path / "d", kind, drive_spec(6))
    data = path.read_bytes()
    if damage.startswith("garbage"):
        path.write_bytes(np.random.default_rng(0).bytes(len(data)))
    elif damage.startswith("truncated"):
        path.write_bytes(data[: len(data) * 2 // 3])
    else:
        path = write_bag(tmp_path / "r2", "ros2-sqlite3", drive_spec(3))
        (path / "metadata.yaml").write_text("not: [a, rosbag2")
    with pytest.raises(InputError) as info:
        src = open_source(path, HOG)
        src.read_all()  # a ROS 1 bag's damaged data is found while reading it
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def _cli(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_ingest_then_geojson_gives_back_the_fixes(tmp_path):
    spec = drive_spec(12, hz=10.0, gnss_hz=10.0)  # a fix at each frame's time
    spec.image_ns = [f.t_ns for f in spec.fixes[1:13]]
    bag = write_bag(tmp_path / "drive", "ros2-sqlite3", spec)
    assert _cli("init", tmp_path / "m", "--descriptor", "hog").exit_code == 0
    done = _cli("ingest", tmp_path / "m", bag, "--json")
    assert done.exit_code == 0, done.output
    out = _cli("export", tmp_path / "m", "--geojson", tmp_path / "m.geojson")
    assert out.exit_code == 0, out.output
    data = json.loads((tmp_path / "m.geojson").read_text())
    assert data["sprint_map"]["crs"] == "EPSG:4326"
    coords = np.array(data["features"][0]["geometry"]["coordinates"])
    want = np.array([[f.lon, f.lat] for f in spec.fixes[1:13]])
    np.testing.assert_allclose(coords, want, atol=1e-8)  # ~1 mm: the projection's round trip
    with SprintMap.open(tmp_path / "m", readonly=True) as m:
        pos = m.positions(0)
        assert pos.shape == (12, 5)
        np.testing.assert_allclose(pos[:, 4], 1.5)  # sigma kept
        np.testing.assert_allclose(np.diff(pos[:, 1]), 1.0, atol=1e-3)  # 10 m/s at 10 Hz
        assert m.geo_frame().zone == 32


def test_bad_bags_leave_the_map_unchanged(tmp_path):
    good = write_bag(tmp_path / "good", "ros1", drive_spec(5))
    trunc = write_bag(tmp_path / "t", "mcap", drive_spec(5))
    trunc.write_bytes(trunc.read_bytes()[:-300])
    assert _cli("init", tmp_path / "m", "--descriptor", "hog").exit_code == 0
    assert _cli("ingest", tmp_path / "m", good).exit_code == 0
    before = _cli("info", tmp_path / "m", "--json").output
    for args in ([trunc], [good, "--image-topic", "/nope"], [good, "--gnss-topic", "/x"]):
        result = _cli("ingest", tmp_path / "m", *args)
        assert result.exit_code == InputError.exit_code
        assert result.output.count("\n") == 1 and result.output.startswith("Error: ")
    after = _cli("info", tmp_path / "m", "--json").output
    assert json.loads(after)["vertices"] == json.loads(before)["vertices"] == 5


def test_localize_a_bag(tmp_path):
    bag = write_bag(tmp_path / "d", "ros1", drive_spec(6))
    assert _cli("init", tmp_path / "m", "--descriptor", "hog").exit_code == 0
    assert _cli("ingest", tmp_path / "m", bag, "--name", "first").exit_code == 0
    result = _cli("localize", tmp_path / "m", bag, "--json", "--image-topic", "/camera/image")
    assert result.exit_code == 0, result.output
    decisions = json.loads(result.output)["decisions"]
    assert len(decisions) == 6




@pytest.mark.parametrize("kind", KINDS)
def test_every_connection_of_the_topics_in_time_order(tmp_path, kind):
    # issue 52 (4): the image topic on two connections (a topic re-advertised, two
    # recordings), the fixes on two: every frame, in time order, with its own time and fix
    spec = drive_spec(12, hz=5.0, gnss_hz=10.0, image_connections=2, gnss_connections=2)
    spec.image_ns = [t + 37_000_000 for t in spec.image_ns]
    one = drive_spec(12, hz=5.0, gnss_hz=10.0)
    one.image_ns = spec.image_ns
    src = open_source(write_bag(tmp_path / "two", kind, spec), HOG, batch_size=5)
    want = open_source(write_bag(tmp_path / "one", kind, one), HOG, batch_size=5)
    assert src.count == src.source_frames == 12
    np.testing.assert_array_equal(src.ordinals, np.arange(12))
    np.testing.assert_allclose(src.read_all(), want.read_all(), atol=1e-6)
    np.testing.assert_allclose(src.positions.time, np.asarray(spec.image_ns) / 1e9)
    t = (np.asarray(spec.image_ns) - spec.fixes[1].t_ns) / 1e9
    np.testing.assert_allclose(src.positions.xy[:, 0], 59.91 + 10.0 * t / 111_320.0,
                               rtol=0, atol=1e-10)  # between fixes of both connections
    kept = open_source(write_bag(tmp_path / "every", kind, spec), HOG, thumbnails=True,
                       bag=_options(every_m=5.0))
    rows = kept.read_all()
    assert kept.positions.frames.tolist() == kept.ordinals.tolist() == [0, 3, 6, 9]
    np.testing.assert_allclose(rows, want.read_all()[[0, 3, 6, 9]], atol=1e-6)
    assert len(kept.thumbnails) == 4


def test_every_m_with_a_positions_file_of_one_row_per_image(tmp_path):
    # issue 52 (5): --every-m with --positions: a CSV of one row per image of the bag was
    # refused ("beyond the drive"), one of one row per kept image stored misaligned
    spec = drive_spec(20, hz=5.0, speed_mps=10.0)  # 2 m between frames: 0, 3, 6, ... kept
    bag = write_bag(tmp_path / "d", "ros1", spec)
    csv = tmp_path / "pos.csv"
    csv.write_text("frame,x,y\n" + "".join(f"{i},{i * 100.0},7\n" for i in range(20)))
    assert _cli("init", tmp_path / "m", "--descriptor", "hog").exit_code == 0
    done = _cli("ingest", tmp_path / "m", bag, "--every-m", 5, "--positions", csv)
    assert done.exit_code == 0, done.output
    with SprintMap.open(tmp_path / "m", readonly=True) as m:
        np.testing.assert_array_equal(m.positions(0)[:, 0], [0, 300, 600, 900, 1200, 1500, 1800])
    for rows, message in ((7, "one per kept frame"), (21, "beyond the drive")):
        csv.write_text("frame,x,y\n" + "".join(f"{i},{i * 100.0},7\n" for i in range(rows)))
        refused = _cli("localize", tmp_path / "m", bag, "--every-m", 5, "--positions", csv)
        assert refused.exit_code == InputError.exit_code, refused.output
        assert refused.output.startswith("Error: ") and message in refused.output
        assert refused.output.count("\n") == 1


@pytest.mark.parametrize("bad", [math.inf, math.nan])
def test_a_fix_with_a_covariance_not_finite_is_not_used(tmp_path, bad):
    # issue 52 (12): one NavSatFix with an inf covariance aborted the whole ingest with an
    # error naming neither the bag nor the topic; it is a fix that does not know where it is
    spec = drive_spec(10, hz=5.0, gnss_hz=10.0)
    spec.image_ns = [t + 50_000_000 for t in spec.image_ns]  # frames between two fixes
    spec.fixes[6].sigma = bad  # the fix at 0.5 s: frame 2 (0.45 s) has no fix
    bag = write_bag(tmp_path / "d", "ros2-mcap", spec)
    src = open_source(bag, HOG)
    assert src.positions.fixed.tolist() == [True, True, False, True, True, True, True, True,
                                            True, True]
    assert np.isfinite(src.positions.sigma_m[src.positions.fixed]).all()
    assert src.warnings == [f"{bag}: topic '/gnss/fix': 1 of {len(spec.fixes)} fixes report "
                            "a covariance that is not finite and were not used (frames near "
                            "them have no fix)"]
    assert _cli("init", tmp_path / "m", "--descriptor", "hog").exit_code == 0
    done = CliRunner().invoke(main, ["ingest", str(tmp_path / "m"), str(bag)])
    assert done.exit_code == 0, done.output + done.stderr
    assert done.stderr.startswith(f"Warning: {bag}: topic '/gnss/fix': 1 of")
    with SprintMap.open(tmp_path / "m", readonly=True) as m:
        pos = m.positions(0)
        assert np.isnan(pos[2, :2]).all() and np.isfinite(pos[[0, 1, 3], :2]).all()
