"""The examples in the package's docstrings run and print what they say (numpydoc
``Examples`` sections): every module whose source holds one is collected."""

from __future__ import annotations

import doctest
import importlib
from pathlib import Path

import pytest

import sprint_map

PACKAGE = Path(sprint_map.__file__).parent
MODULES = sorted(
    ".".join(("sprint_map", *path.relative_to(PACKAGE).with_suffix("").parts))
    for path in PACKAGE.rglob("*.py")
    if ">>> " in path.read_text(encoding="utf-8")
)


def test_the_package_has_examples():
    assert "sprint_map.merge.verification" in MODULES and "sprint_map.merge.rule" in MODULES


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name):
    module = importlib.import_module(name)
    finder = doctest.DocTestFinder(exclude_empty=True)
    runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    tests = [t for t in finder.find(module, name) if t.examples]
    assert tests, f"{name} holds '>>> ' but no example was found"
    for test in tests:
        runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {name}"


def test_the_facade_is_shown_by_example():
    """The user's API is a reference with examples (networkx is the model): at least 20 of
    ``SprintMap``'s public methods carry one that runs above (51 when this was written)."""
    from sprint_map import SprintMap

    shown = [name for name in dir(SprintMap) if not name.startswith("_")
             and ">>> " in (getattr(getattr(SprintMap, name), "__doc__", None) or "")]
    assert len(shown) >= 20, shown
