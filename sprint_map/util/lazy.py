"""The package's one lazy loader: modules and names imported on first use.

Two forms of one idea, so that a command loads only what it runs (``tests/test_startup.py``):

* :func:`lazy_module` gives an object that stands for a module: the first attribute read
  imports it (Python's import lock makes that safe from several threads), every read after that
  is an attribute read on the module (O(1), well under a microsecond next to any call).
  ``from sprint_map.util.lazy import faiss`` is FAISS so: ``sprint-map info`` opens a map and
  describes its index from file names and sizes, so it never reads an attribute and never pays
  for FAISS's ~0.1 s import (``tools/bench_startup.py``).
* :func:`lazy_names` gives a package the module ``__getattr__`` and ``__dir__`` of PEP 562 for
  the public names it re-exports from its modules: each is imported by its first read and kept
  in the package's namespace (later reads are plain attribute reads).

Examples
--------
>>> json = lazy_module("json")
>>> json.dumps([1])
'[1]'
>>> getattr_, dir_ = lazy_names("sprint_map.util", {"UnionFind": "sprint_map.util.union_find"})
>>> getattr_("UnionFind").__name__
'UnionFind'
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping
from types import ModuleType
from typing import Any

__all__ = ["faiss", "lazy_module", "lazy_names"]


class _LazyModule:
    """A module imported by its first attribute read."""

    __slots__ = ("_module", "_name")

    def __init__(self, name: str) -> None:
        self._name = name
        self._module: ModuleType | None = None

    def __getattr__(self, attr: str) -> Any:
        module = self._module
        if module is None:
            module = self._module = importlib.import_module(self._name)
        return getattr(module, attr)

    def __repr__(self) -> str:
        state = "imported" if self._module is not None else "not imported yet"
        return f"<lazy module {self._name!r} ({state})>"


def lazy_module(name: str) -> Any:
    """An object standing for the module ``name``, imported by its first attribute read."""
    return _LazyModule(name)


def lazy_names(package: str, homes: Mapping[str, str]
               ) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The ``__getattr__`` and ``__dir__`` of ``package`` that import each name of ``homes``
    (name -> the module defining it) on first use; any other name is an AttributeError."""

    def __getattr__(name: str) -> Any:
        home = homes.get(name)
        if home is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(home), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        namespace = vars(sys.modules[package])
        return sorted(set(namespace) | set(namespace.get("__all__", ())))

    return __getattr__, __dir__


#: The ``faiss`` module, imported on first use.
faiss: Any = lazy_module("faiss")
