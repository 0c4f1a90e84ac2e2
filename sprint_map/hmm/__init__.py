"""The SPRINT hidden Markov model: place recognition over the active subgraphs of the map.

This package knows nothing of storage or retrieval: it reads components through
:class:`GraphSource` and takes retrieval hits as arrays. See ``docs/hmm.md`` ("The HMM").
"""

from sprint_map.hmm.cache import ComponentCache
from sprint_map.hmm.config import HMMConfig
from sprint_map.hmm.decision import Decision
from sprint_map.hmm.full_graph import FullGraphFilter
from sprint_map.hmm.graph import ComponentGraph, GraphSource, MemoryGraphSource
from sprint_map.hmm.observation import Observation, ObservationModel
from sprint_map.hmm.sprint_filter import SprintFilter

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
