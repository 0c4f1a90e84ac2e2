"""The layout of ``tests/``: it mirrors the package, and every test module has a name of its own.

pytest imports every test module by its file name alone (``tests/`` holds no packages, only
``tests/helpers``), so two ``test_x.py`` in different folders stop the whole run at collection.
A test of ``sprint_map/x/`` lives in ``tests/x/``, a test of ``tools/`` in ``tests/tools/``;
the top of ``tests/`` holds only the tests of the top-level modules (``map.py``, ``config.py``)
and the checks of the project as a whole. Code is imported by name (``tests.helpers.x``,
``tools.x``), never loaded from a file path.
"""

from __future__ import annotations

import re
from collections import defaultdict
from pathlib import Path

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent
#: The checks of the project as a whole (docs, layout, public names, start-up, text decoding,
#: running without OpenCV): they belong to no one package.
PROJECT = {"architecture", "docs", "docstrings", "doctests", "public_api", "readme", "startup",
           "test_modules", "text_input", "without_opencv"}
#: What loads code from a path: ``sys.path`` edits and ``importlib``'s file loaders.
BY_PATH = re.compile(r"sys\.path\.(?:insert|append)\(|spec_from_file_location\(|"
                     r"SourceFileLoader\(|run_path\(")


def test_every_test_module_has_a_name_of_its_own():
    folders: dict[str, list[str]] = defaultdict(list)
    for path in TESTS.rglob("test_*.py"):
        folders[path.name].append(path.parent.relative_to(TESTS).as_posix())
    clashes = {name: sorted(where) for name, where in folders.items() if len(where) > 1}
    assert not clashes, f"test modules named alike in several folders: {clashes}"


def test_each_folder_of_tests_is_a_package_or_the_tools():
    folders = {p.parent.relative_to(TESTS).parts[0] for p in TESTS.glob("*/**/test_*.py")}
    packages = {d.name for d in (ROOT / "sprint_map").iterdir() if (d / "__init__.py").is_file()}
    assert folders <= packages | {"tools"}, sorted(folders - packages - {"tools"})


def test_the_top_of_tests_holds_only_top_level_modules_and_project_checks():
    modules = {f.stem for f in (ROOT / "sprint_map").glob("*.py") if f.stem != "__init__"}
    misplaced = []
    for path in sorted(TESTS.glob("test_*.py")):
        topic = path.stem.removeprefix("test_")
        if topic not in PROJECT and not any(topic == m or topic.startswith(f"{m}_")
                                            for m in modules):
            misplaced.append(path.name)
    assert not misplaced, f"move these into the folder of the package they test: {misplaced}"
    assert not [p.name for p in TESTS.glob("*.py") if not p.name.startswith(("test_", "conftest"))]


def test_no_test_loads_code_by_path():
    loaders = [f"{p.relative_to(ROOT)}:{text.count(chr(10), 0, m.start()) + 1}"
               for p in sorted(TESTS.rglob("*.py")) if p != Path(__file__).resolve()
               for text in [p.read_text(encoding="utf-8")] for m in BY_PATH.finditer(text)]
    assert not loaders, f"import these by name instead: {loaders}"


def test_every_module_the_rng_seeds_by_its_old_path_exists():
    from tests.conftest import MOVED_FROM_TOP

    assert all((TESTS / path).is_file() for path in MOVED_FROM_TOP)
    assert not [p for p in MOVED_FROM_TOP if (TESTS / p.rpartition("/")[2]).exists()]
