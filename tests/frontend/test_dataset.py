"""Data sets on disk and their ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from sprint_map.errors import ConfigError, InputError
from sprint_map.evaluation.demo import find_nordland
from sprint_map.frontend import Dataset, DescriptorSpec, GroundTruth, GroundTruthSpec

NORDLAND = find_nordland() or Path("/nonexistent/nordland")  # ../shared/data/nordland in CI


def make_images(folder: Path, count: int, seed: int = 0) -> None:
    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    for i in range(count):
        cv2.imwrite(str(folder / f"{i}.png"), rng.integers(0, 256, (24, 32), dtype=np.uint8))


def write_positions(folder: Path, rows: list[tuple[float, ...]]) -> None:
    header = "frame,x,y" + (",heading_deg" if len(rows[0]) == 3 else "")
    lines = [header] + [",".join(str(v) for v in (i, *row)) for i, row in enumerate(rows)]
    (folder / "positions.csv").write_text("\n".join(lines) + "\n")


@pytest.fixture
def dataset_dir(tmp_path) -> Path:
    """Three traversals of different kinds, with positions, and a README to ignore."""
    root = tmp_path / "set"
    make_images(root / "run10", 4)
    make_images(root / "run2", 3, seed=1)
    write_positions(root / "run10", [(0, 0, 0), (5, 0, 0), (10, 0, 0), (11, 0, 180)])
    write_positions(root / "run2", [(1, 0, 0), (9, 0, 0), (40, 0, 0)])
    (root / "run3").mkdir()
    np.save(root / "run3" / "descriptors.npy", np.ones((2, 1764), np.float32))
    write_positions(root / "run3", [(0, 1, 90), (0, 2, 90)])
    (root / "README.md").write_text("about this set")
    (root / ".cache").mkdir()
    (root / "dataset.json").write_text(
        json.dumps({"alignment": "position", "radius_m": 3, "heading_deg": 45, "description": "t"})
    )
    return root


def test_open_lists_traversals_in_natural_order(dataset_dir):
    dataset = Dataset.open(dataset_dir)
    assert dataset.names == ["run2", "run3", "run10"]
    assert len(dataset) == 3 and [t.name for t in dataset] == dataset.names
    assert [t.kind for t in dataset] == ["images", "npy", "images"]
    assert [t.count for t in dataset] == [3, 2, 4]
    assert dataset.gt_spec == GroundTruthSpec("position", radius_m=3, heading_deg=45)
    assert dataset.info == {"description": "t"}
    source = dataset["run10"].open(DescriptorSpec("hog"), workers=1)
    assert source.name == "run10" and source.read_all().shape == (4, 1764)
    assert dataset["run3"].open().name == "run3"
    with pytest.raises(InputError, match="no traversal 'run4'"):
        dataset["run4"]


def test_position_ground_truth(dataset_dir):
    gt = Dataset.open(dataset_dir).ground_truth()
    # run2 frame 0 is at x=1: within 3 m of run10 frames 0 (x=0); frame 1 (x=9) of frame 2 (x=10).
    np.testing.assert_array_equal(gt.matches("run2", 0, "run10"), [0])
    np.testing.assert_array_equal(gt.matches("run2", 1, "run10"), [2])
    assert gt.matches("run2", 2, "run10").size == 0  # x=40: a place run10 never saw
    np.testing.assert_array_equal(
        gt.correct("run2", [[0], [1]], "run10", [[0, 1, 2], [1, 2, 3]]),
        [[True, False, False], [False, True, False]],
    )
    np.testing.assert_array_equal(gt.has_match("run2", [0, 1, 2], "run10"), [True, True, False])
    np.testing.assert_array_equal(
        gt.has_match("run2", [0, 1, 2], ["run10", "run3"]), [True, True, False]
    )


def test_heading_tolerance(dataset_dir):
    gt = Dataset.open(dataset_dir).ground_truth()
    # run10 frame 3 (x=11, heading 180) and frame 2 (x=10, heading 0): 1 m apart, opposite ways.
    assert gt.correct("run10", 3, "run10", 3)
    assert not gt.correct("run10", 3, "run10", 2)
    assert (
        Dataset.open(dataset_dir, {"heading_deg": 180})
        .ground_truth()
        .correct("run10", 3, "run10", 2)
    )
    assert gt.matches("run3", 0, "run10").size == 0  # (0, 1) heading 90 vs run10 (0, 0) heading 0
    loose = Dataset.open(dataset_dir, {"heading_deg": 90}).ground_truth()
    np.testing.assert_array_equal(loose.matches("run3", 0, "run10"), [0])


def test_heading_tolerance_needs_headings(tmp_path):
    root = tmp_path / "set"
    make_images(root / "a", 2)
    write_positions(root / "a", [(0, 0), (1, 0)])
    dataset = Dataset.open(root, {"alignment": "position", "heading_deg": 30})
    with pytest.raises(InputError, match="no heading_deg"):
        dataset.ground_truth().matches("a", 0, "a")
    assert (
        Dataset.open(root, {"alignment": "position"}).ground_truth().matches("a", 0, "a").size == 2
    )


def test_missing_positions_reported_on_use(tmp_path):
    root = tmp_path / "set"
    make_images(root / "a", 2)
    gt = Dataset.open(root, {"alignment": "position"}).ground_truth()
    with pytest.raises(InputError, match="no positions.csv"):
        gt.matches("a", 0, "a")


def test_frame_alignment_with_override_and_stride(tmp_path):
    root = tmp_path / "set"
    make_images(root / "summer", 10)
    make_images(root / "winter", 8)
    dataset = Dataset.open(root, {"alignment": "frame", "tolerance_frames": 1})
    gt = dataset.ground_truth()
    np.testing.assert_array_equal(gt.matches("winter", 5, "summer"), [4, 5, 6])
    np.testing.assert_array_equal(gt.matches("summer", 0, "winter"), [0, 1])
    np.testing.assert_array_equal(gt.matches("summer", 9, "winter"), [])  # winter ends at 7
    np.testing.assert_array_equal(gt.has_match("summer", [7, 8, 9], "winter"), [True, True, False])
    np.testing.assert_array_equal(
        gt.correct("winter", [[5]], "summer", [[3, 4, 5, 6, 7]]), [[False, True, True, True, False]]
    )
    # With stride 2 ingested frame i is original frame 2i: +/-1 original frame is only i itself.
    strided = dataset.ground_truth(stride=2)
    np.testing.assert_array_equal(strided.matches("winter", 2, "summer"), [2])
    assert strided.matches("summer", 4, "winter").size == 0  # winter has 4 frames at stride 2


def test_stride_subsamples_positions(dataset_dir):
    gt = Dataset.open(dataset_dir).ground_truth(stride=2)
    # At stride 2, run10 keeps original frames 0 and 2 (x=0, x=10), run2 frames 0 and 2 (x=1, 40).
    np.testing.assert_array_equal(gt.matches("run2", 0, "run10"), [0])
    np.testing.assert_array_equal(gt.matches("run10", 1, "run10"), [1])
    assert gt.matches("run2", 1, "run10").size == 0


def test_no_ground_truth_declared(tmp_path):
    root = tmp_path / "set"
    make_images(root / "a", 1)
    dataset = Dataset.open(root)
    assert dataset.gt_spec is None
    with pytest.raises(InputError, match="no ground truth declared"):
        dataset.ground_truth()


@pytest.mark.parametrize(
    "content",
    ["{not json", "[1, 2]", '{"alignment": "gps"}', '{"alignment": "frame", "tolerance": 1}'],
)
def test_invalid_dataset_json_names_the_file(tmp_path, content):
    root = tmp_path / "set"
    make_images(root / "a", 1)
    (root / "dataset.json").write_text(content)
    with pytest.raises(InputError, match="dataset.json"):
        Dataset.open(root)


@pytest.mark.parametrize(
    "override", [{"tolerance_frames": 1}, {"alignment": "frame", "tolerance_frames": -1}]
)
def test_invalid_override(tmp_path, override):
    root = tmp_path / "set"
    make_images(root / "a", 1)
    with pytest.raises(ConfigError):
        Dataset.open(root, override)


def test_video_traversal_and_ambiguous_folders(tmp_path):
    root = tmp_path / "set"
    (root / "drive").mkdir(parents=True)
    writer = cv2.VideoWriter(
        str(root / "drive" / "cam.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 5, (32, 24)
    )
    for i in range(6):
        writer.write(np.full((24, 32, 3), i * 40, np.uint8))
    writer.release()
    write_positions(root / "drive", [(i, 0) for i in range(6)])
    dataset = Dataset.open(root, {"alignment": "position"})
    traversal = dataset["drive"]
    assert (traversal.kind, traversal.count, traversal.source_path.name) == (
        "video",
        None,
        "cam.avi",
    )
    assert traversal.positions().shape == (6, 3)  # row count trusted for a video
    assert traversal.positions(stride=4)[:, 0].tolist() == [0, 4]
    assert traversal.open(workers=1).read_all().shape == (6, 1764)

    (root / "drive" / "other.mp4").write_bytes(b"")
    with pytest.raises(InputError, match="ambiguous"):
        Dataset.open(root)


@pytest.mark.parametrize("setup", ["no-traversals", "empty-traversal", "missing"])
def test_unusable_data_sets(tmp_path, setup):
    root = tmp_path / "set"
    if setup != "missing":
        root.mkdir()
        (root / "README.md").write_text("x")
    if setup == "empty-traversal":
        (root / "a").mkdir()
        (root / "a" / "notes.txt").write_text("x")
    with pytest.raises(InputError, match=str(root)):
        Dataset.open(root)


def test_ground_truth_without_a_dataset():
    spec = GroundTruthSpec.from_dict({"alignment": "position", "radius_m": 2})
    positions = {"a": np.array([[0, 0, 0], [1, 5, 0]], float), "b": np.array([[0, 4, 0]], float)}
    gt = GroundTruth(spec, positions=positions)
    np.testing.assert_array_equal(gt.matches("b", 0, "a"), [1])
    with pytest.raises(InputError, match="no positions for traversal 'c'"):
        gt.matches("c", 0, "a")
    with pytest.raises(ConfigError):
        GroundTruth(spec)
    assert GroundTruthSpec.from_dict(spec.to_dict()) == spec


@pytest.mark.slow
@pytest.mark.skipif(not NORDLAND.is_dir(), reason="Nordland data not available")
def test_nordland_summer_to_winter_hog_knn():
    """The README's reference: HoG 64x64, exact search, +/-1 frame: k-NN@1 41.4 %, @10 64.4 %."""
    dataset = Dataset.open(NORDLAND, {"alignment": "frame", "tolerance_frames": 1})
    assert dataset.names == ["summer", "winter"]
    spec = DescriptorSpec("hog")
    summer = dataset["summer"].open(spec).read_all()
    winter = dataset["winter"].open(spec).read_all()
    assert summer.shape == winter.shape == (3576, 1764)
    dist = (winter**2).sum(1)[:, None] - 2 * winter @ summer.T + (summer**2).sum(1)
    order = np.argsort(dist, axis=1, kind="stable")[:, :10]
    correct = dataset.ground_truth().correct("winter", np.arange(3576)[:, None], "summer", order)
    assert correct[:, 0].mean() == pytest.approx(0.414, abs=0.002)
    assert correct.any(axis=1).mean() == pytest.approx(0.644, abs=0.002)


def test_twin_frames_from_dataset_json(dataset_dir):
    assert Dataset.open(dataset_dir).twin_frames("run10") is None  # none declared
    info = json.loads((dataset_dir / "dataset.json").read_text())
    info["twins"] = {"run10": [[1, 3]]}
    (dataset_dir / "dataset.json").write_text(json.dumps(info))
    data = Dataset.open(dataset_dir)
    assert data.twin_frames("run10").tolist() == [False, True, True, False]
    assert data.twin_frames("run10", stride=2).tolist() == [False, True]
    assert data.twin_frames("run2").tolist() == [False, False, False]  # not listed: none
    info["twins"] = {"run10": [[1]]}
    (dataset_dir / "dataset.json").write_text(json.dumps(info))
    with pytest.raises(InputError, match="twins"):
        Dataset.open(dataset_dir).twin_frames("run10")


def test_frame_ranges_round_trip():
    from sprint_map.frontend.dataset import frame_ranges

    mask = np.array([1, 1, 0, 0, 1, 0, 1, 1, 1], dtype=bool)
    assert frame_ranges(mask) == [[0, 2], [4, 5], [6, 9]]
    assert frame_ranges(np.zeros(3, dtype=bool)) == []
