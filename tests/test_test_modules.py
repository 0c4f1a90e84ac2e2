"""pytest imports every test module by its file name alone (``tests/`` holds no packages, only
``tests/helpers``), so two ``test_x.py`` in different folders stop the whole run at collection."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

TESTS = Path(__file__).resolve().parent


def test_every_test_module_has_a_name_of_its_own():
    folders: dict[str, list[str]] = defaultdict(list)
    for path in TESTS.rglob("test_*.py"):
        folders[path.name].append(path.parent.relative_to(TESTS).as_posix())
    clashes = {name: sorted(where) for name, where in folders.items() if len(where) > 1}
    assert not clashes, f"test modules named alike in several folders: {clashes}"
