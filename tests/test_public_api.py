"""Every module of the package declares its public names (``__all__``), and they are real.

mypy's strict mode (no implicit re-export) makes ``__all__`` the contract for what other modules
may import; this test keeps it declared, resolvable and free of private names, module by module
(py-lmdb's package test pinning ``__all__`` is the model; ``tests/test_readme.py`` pins the
top-level names themselves)."""

from __future__ import annotations

import importlib
import importlib.util
import pkgutil

import pytest

import sprint_map


def _module_names() -> list[str]:
    names = [sprint_map.__name__]
    # onerror: a subpackage that cannot be imported for walking is imported (and reported) below.
    for info in pkgutil.walk_packages(sprint_map.__path__, prefix="sprint_map.",
                                      onerror=lambda name: None):
        names.append(info.name)
    return sorted(names)


MODULES = _module_names()


def _import(name: str):
    """Import ``name``; skip only when it needs an optional extra that is truly not installed."""
    try:
        return importlib.import_module(name)
    except ModuleNotFoundError as error:
        top = (error.name or "").partition(".")[0]
        if top and top != "sprint_map" and importlib.util.find_spec(top) is None:
            pytest.skip(f"{name} needs {top!r}, an optional extra not installed here")
        raise


def test_the_walk_finds_the_whole_package():
    # Every layer is walked (a broken walk would make the test below vacuous).
    for name in ("sprint_map.cli.main", "sprint_map.map", "sprint_map.storage.store",
                 "sprint_map.hmm.sprint_filter", "sprint_map.server.app", "sprint_map.fleet.farm",
                 "sprint_map.frontend.sources", "sprint_map.synth.city", "sprint_map.localize.trace"):
        assert name in MODULES
    assert len(MODULES) > 80


@pytest.mark.parametrize("name", MODULES)
def test_module_declares_its_public_names(name):
    module = _import(name)
    assert "__all__" in vars(module), f"{name} does not declare __all__"
    public = module.__all__
    assert isinstance(public, list), f"{name}.__all__ is a {type(public).__name__}, not a list"
    assert len(set(public)) == len(public), f"{name}.__all__ lists a name twice"
    private = [n for n in public if n.startswith("_")]
    assert not private, f"{name}.__all__ lists private names {private}"
    missing = [n for n in public if not hasattr(module, n)]
    assert not missing, f"{name}.__all__ lists names it does not define: {missing}"
