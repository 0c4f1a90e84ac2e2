"""FAISS, imported on first use, so that commands which only read LMDB never load it.

``from sprint_map.util.lazy_faiss import faiss`` gives an object that stands for the
``faiss`` module: the first attribute read imports it (Python's import lock makes that safe
from several threads), every read after that is an attribute read on the module (O(1), well
under a microsecond next to any FAISS call). ``sprint-map info`` opens a map and describes its
index from file names and sizes, so it never reads an attribute and never pays for FAISS's
~0.1 s import (``tools/bench_startup.py``, ``tests/test_startup.py``).
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import Any

__all__ = ["faiss"]


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


#: The ``faiss`` module, imported on first use.
faiss: Any = _LazyModule("faiss")
