"""What ``import sprint_map`` loads: the facade's configuration, not the image front end."""

from __future__ import annotations

import subprocess
import sys


def loaded_after(statement: str) -> set[str]:
    code = f"import sys; {statement}; print(' '.join(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    return set(out.split())


def test_import_sprint_map_loads_neither_opencv_nor_data_sets():
    mods = loaded_after("import sprint_map")
    assert "cv2" not in mods and "scipy.spatial" not in mods
    assert "sprint_map.frontend.dataset" not in mods


def test_the_front_end_loads_opencv_when_an_image_is_described():
    mods = loaded_after(
        "import numpy as np; from sprint_map.frontend import DescriptorSpec; "
        "DescriptorSpec('hog').describe(np.zeros((48, 64, 3), np.uint8))")
    assert "cv2" in mods


def test_nothing_imports_ray_without_ray_asked_for():
    """Ray (the optional extra) loads only with ``--ray`` or sprint_map.fleet's functions."""
    mods = loaded_after("import sprint_map.cli, sprint_map.map, sprint_map.fleet.runtime, "
                        "sprint_map.fleet.shards")
    assert "ray" not in mods
