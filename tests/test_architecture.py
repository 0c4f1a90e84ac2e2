"""The layer diagram of ``docs/architecture.md`` ("Layers") names the package tree as it is:
every package and top-level module of ``sprint_map/``, and nothing that does not exist."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "sprint_map"
DOC = ROOT / "docs" / "architecture.md"
#: A path in the diagram: ``sprint_map/x/`` (a package) or ``sprint_map/x.py`` (a module).
NAMED = re.compile(r"\bsprint_map/(?:[a-z_]+/)*(?:[a-z_]+\.py|)(?=\s)")


def layer_diagram(text: str) -> str:
    """The first code block of the "Layers" section."""
    section = text.split("\n## Layers\n", 1)[1].split("\n## ", 1)[0]
    return section.split("```", 2)[1]


def named_paths(diagram: str) -> list[str]:
    """The paths the diagram names, in order (one per line, the line's first word)."""
    return [m.group(0) for line in diagram.splitlines()
            if (m := NAMED.match(line.strip())) is not None]


def tree() -> set[str]:
    """Every package (``sprint_map/x/``, ``sprint_map/x/y/``) and top-level module."""
    packages = {f"{d.relative_to(ROOT).as_posix()}/" for d in PACKAGE.rglob("*")
                if d.is_dir() and (d / "__init__.py").is_file()}
    modules = {f"sprint_map/{f.name}" for f in PACKAGE.glob("*.py") if f.name != "__init__.py"}
    return packages | modules


def test_the_diagram_names_every_package_and_top_level_module():
    named = named_paths(layer_diagram(DOC.read_text()))
    missing = tree() - set(named)
    assert not missing, f"docs/architecture.md's layer diagram leaves out {sorted(missing)}"


def test_everything_the_diagram_names_exists_once():
    named = named_paths(layer_diagram(DOC.read_text()))
    absent = [p for p in named if not (ROOT / p).exists()]
    assert not absent, f"docs/architecture.md's layer diagram names {absent}: not in the tree"
    assert len(named) == len(set(named)), "a path named twice"


@pytest.mark.parametrize("diagram, named", [
    ("```\nlayer\n  sprint_map/util/   x\n  sprint_map/map.py  facade\n```",
     ["sprint_map/util/", "sprint_map/map.py"]),
    ("  sprint_map/storage/index/  y\n  not sprint_map/cli/ here\n", ["sprint_map/storage/index/"]),
])
def test_paths_are_read_from_the_start_of_each_line(diagram, named):
    assert named_paths(diagram) == named
