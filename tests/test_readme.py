"""The README's promises: its Python blocks run, and the package's public names are these."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

import sprint_map

README = Path(__file__).resolve().parents[1] / "README.md"


def python_blocks() -> list[str]:
    return re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


def test_readme_python_blocks_run(tmp_path, monkeypatch):
    """Every ```python block of the README runs as written, in a fresh directory, given the
    drives it names (random descriptors of the dimension it uses)."""
    blocks = python_blocks()
    assert blocks, "the README has no Python example"
    monkeypatch.chdir(tmp_path)
    rng = np.random.default_rng(0)
    road = rng.standard_normal((120, 256)).astype(np.float32)
    names = {
        "first_drive": road,
        "second_drive": road + 0.05 * rng.standard_normal(road.shape).astype(np.float32),
        "descriptor": road[10] + 0.05 * rng.standard_normal(256).astype(np.float32),
    }
    for block in blocks:
        scope = dict(names)
        exec(compile(block, str(README), "exec"), scope)  # noqa: S102 - the README's own code
    assert scope["result"].added.sequence.name == "tue"
    assert scope["decision"].seq_id in (0, 1)


#: The user's names: the facade, its configuration and its records.
USER_NAMES = [
    "AddResult", "CheckReport", "CompactReport", "ComponentInfo", "Drive", "EdgeInfo",
    "EdgeSpec", "FrameDecision", "HMMConfig", "IngestResult", "Localizer", "MapConfig",
    "RemoveResult", "RepairReport", "SCHEMA_VERSION", "SequenceRecord", "SprintMap",
    "SprintMapError", "Timing", "UnmergeResult"]
#: The doors of the layers on top (cli, server, fleet, evaluation, viewer) to those below.
DOOR_NAMES = [
    "BagOptions", "Dataset", "DescriptorSpec", "DriveCentring", "DriveLocalisation",
    "DriveWriter", "GnssModel", "GroundTruth", "LaggedLocalizer", "LocaliseMany",
    "MAX_IMAGE_PIXELS", "MAX_LAG", "MapService", "PreparedDrive", "Trace", "TraceRecorder",
    "Traversal", "VprDataset", "describe_encoded", "drive_names", "drive_positions",
    "gnss_fixes", "onnx_params", "own_positions", "read_trace", "simulate_fixes",
    "validate_lag"]


def test_public_names():
    assert sorted(sprint_map.__all__) == sorted(USER_NAMES + DOOR_NAMES)
    for name in sprint_map.__all__:
        assert getattr(sprint_map, name) is not None
    assert (Path(sprint_map.__file__).parent / "py.typed").is_file()
