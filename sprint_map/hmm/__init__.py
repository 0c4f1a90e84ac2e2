"""The SPRINT hidden Markov model: place recognition over the active subgraphs of the map.

This package knows nothing of storage or retrieval: it reads components through
:class:`GraphSource` and takes retrieval hits as arrays. See ``docs/hmm.md`` ("The HMM").

Its names are imported on first use (PEP 562): ``from sprint_map.hmm.config import HMMConfig``
(what a map's configuration needs) loads neither SciPy nor the filters.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from sprint_map.util.lazy import lazy_names

if TYPE_CHECKING:
    from sprint_map.hmm.cache import ComponentCache
    from sprint_map.hmm.config import HMMConfig
    from sprint_map.hmm.decision import Decision
    from sprint_map.hmm.full_graph import FullGraphFilter
    from sprint_map.hmm.graph import ComponentGraph, GraphSource, MemoryGraphSource
    from sprint_map.hmm.observation import Observation, ObservationModel
    from sprint_map.hmm.sprint_filter import SprintFilter

#: Public name -> the module defining it.
_MODULES = {
    "ComponentCache": "cache",
    "ComponentGraph": "graph",
    "Decision": "decision",
    "FullGraphFilter": "full_graph",
    "GraphSource": "graph",
    "HMMConfig": "config",
    "MemoryGraphSource": "graph",
    "Observation": "observation",
    "ObservationModel": "observation",
    "SprintFilter": "sprint_filter",
}

__all__ = [
    "ComponentCache",
    "ComponentGraph",
    "Decision",
    "FullGraphFilter",
    "GraphSource",
    "HMMConfig",
    "MemoryGraphSource",
    "Observation",
    "ObservationModel",
    "SprintFilter",
]


__getattr__, __dir__ = lazy_names(__name__, {name: f"{__name__}.{module}"
                                             for name, module in _MODULES.items()})
