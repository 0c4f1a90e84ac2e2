"""sprint-map: a persistent, lifelong visual place-recognition map (SPRINT, Latif et al. 2020).

The front door is :class:`SprintMap`::

    from sprint_map import MapConfig, SprintMap

The facade and its records (the storage layer's are defined in
:mod:`sprint_map.storage.records`) are imported on first use (PEP 562), so ``import sprint_map``
stays as light as its configuration.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from sprint_map.config import SCHEMA_VERSION, MapConfig
from sprint_map.errors import SprintMapError
from sprint_map.hmm.config import HMMConfig
from sprint_map.util.lazy import lazy_names

if TYPE_CHECKING:
    from sprint_map.localize.localizer import FrameDecision, Localizer, Timing
    from sprint_map.map import SprintMap
    from sprint_map.merge.commit import IngestResult
    from sprint_map.merge.drives import Drive
    from sprint_map.storage.records import (
        AddResult,
        CheckReport,
        CompactReport,
        ComponentInfo,
        EdgeInfo,
        EdgeSpec,
        RemoveResult,
        RepairReport,
        SequenceRecord,
        UnmergeResult,
    )

#: The records the facade's methods return (or take: ``EdgeSpec``).
_RECORDS = ("AddResult", "CheckReport", "CompactReport", "ComponentInfo", "EdgeInfo", "EdgeSpec",
            "RemoveResult", "RepairReport", "SequenceRecord", "UnmergeResult")

__all__ = ["SCHEMA_VERSION", "AddResult", "CheckReport", "CompactReport", "ComponentInfo",
           "Drive", "EdgeInfo", "EdgeSpec", "FrameDecision", "HMMConfig", "IngestResult",
           "Localizer", "MapConfig", "RemoveResult", "RepairReport", "SequenceRecord",
           "SprintMap", "SprintMapError", "Timing", "UnmergeResult"]
__version__ = "0.1.0"

#: Names imported on first use, and the module that defines each.
_LAZY = {"SprintMap": "sprint_map.map", "IngestResult": "sprint_map.merge.commit",
         "Drive": "sprint_map.merge.drives",
         "Localizer": "sprint_map.localize.localizer", "FrameDecision": "sprint_map.localize.localizer",
         "Timing": "sprint_map.localize.localizer",
         **dict.fromkeys(_RECORDS, "sprint_map.storage.records")}


__getattr__, __dir__ = lazy_names(__name__, _LAZY)
