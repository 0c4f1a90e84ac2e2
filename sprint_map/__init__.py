"""sprint-map: a persistent, lifelong visual place-recognition map (SPRINT, Latif et al. 2020).

The front door is :class:`SprintMap`::

    from sprint_map import MapConfig, SprintMap

The layers on top (``cli``, ``server``, ``fleet``, ``evaluation``, ``viewer``) come in by this
door too: the names of the layers below that they use are re-exported here (the ``doors``, by
the module that defines each), so none of them imports ``merge``, ``localize``, ``storage``,
``frontend`` or ``hmm`` itself (the import-linter contract ``facade``). Every name but the
configuration is imported on first use (PEP 562), so ``import sprint_map`` stays as light as
its configuration.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from sprint_map.config import SCHEMA_VERSION, MapConfig
from sprint_map.errors import SprintMapError
from sprint_map.hmm.config import HMMConfig
from sprint_map.util.lazy import lazy_names

if TYPE_CHECKING:
    from sprint_map.facade.service import MapService
    from sprint_map.frontend.bags import BagOptions
    from sprint_map.frontend.centring import DriveCentring
    from sprint_map.frontend.dataset import Dataset, Traversal
    from sprint_map.frontend.descriptors import DescriptorSpec
    from sprint_map.frontend.gnss import GnssModel, simulate_fixes
    from sprint_map.frontend.groundtruth import GroundTruth
    from sprint_map.frontend.image_path import describe_encoded
    from sprint_map.frontend.imageheader import MAX_IMAGE_PIXELS
    from sprint_map.frontend.onnx_model import onnx_params
    from sprint_map.frontend.positions import gnss_fixes
    from sprint_map.frontend.sources import drive_names, drive_positions, own_positions
    from sprint_map.frontend.vpr import VprDataset
    from sprint_map.localize.lagged import MAX_LAG, LaggedLocalizer, validate_lag
    from sprint_map.localize.localizer import FrameDecision, Localizer, Timing
    from sprint_map.localize.trace import Trace, TraceRecorder, read_trace
    from sprint_map.map import SprintMap
    from sprint_map.merge.commit import DriveWriter, IngestResult
    from sprint_map.merge.drives import Drive
    from sprint_map.merge.join import DriveLocalisation, LocaliseMany
    from sprint_map.merge.prepared import PreparedDrive
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

#: The user's names: the facade, its configuration and what its methods take and return.
_USER = {"SprintMap": "sprint_map.map", "IngestResult": "sprint_map.merge.commit",
         "Drive": "sprint_map.merge.drives",
         "Localizer": "sprint_map.localize.localizer", "FrameDecision": "sprint_map.localize.localizer",
         "Timing": "sprint_map.localize.localizer",
         **dict.fromkeys(_RECORDS, "sprint_map.storage.records")}

#: The doors of the layers on top: each name they use of the layers below, and its module.
_DOORS = {
    "MapService": "sprint_map.facade.service",
    "DriveWriter": "sprint_map.merge.commit",
    "PreparedDrive": "sprint_map.merge.prepared",
    "DriveLocalisation": "sprint_map.merge.join", "LocaliseMany": "sprint_map.merge.join",
    **dict.fromkeys(("MAX_LAG", "LaggedLocalizer", "validate_lag"), "sprint_map.localize.lagged"),
    **dict.fromkeys(("Trace", "TraceRecorder", "read_trace"), "sprint_map.localize.trace"),
    "BagOptions": "sprint_map.frontend.bags",
    "DriveCentring": "sprint_map.frontend.centring",
    "Dataset": "sprint_map.frontend.dataset", "Traversal": "sprint_map.frontend.dataset",
    "DescriptorSpec": "sprint_map.frontend.descriptors",
    "GnssModel": "sprint_map.frontend.gnss", "simulate_fixes": "sprint_map.frontend.gnss",
    "GroundTruth": "sprint_map.frontend.groundtruth",
    "describe_encoded": "sprint_map.frontend.image_path",
    "MAX_IMAGE_PIXELS": "sprint_map.frontend.imageheader",
    "onnx_params": "sprint_map.frontend.onnx_model",
    "gnss_fixes": "sprint_map.frontend.positions",
    **dict.fromkeys(("drive_names", "drive_positions", "own_positions"),
                    "sprint_map.frontend.sources"),
    "VprDataset": "sprint_map.frontend.vpr",
}

__all__ = ["MAX_IMAGE_PIXELS", "MAX_LAG", "SCHEMA_VERSION", "AddResult", "BagOptions",
           "CheckReport", "CompactReport", "ComponentInfo", "Dataset", "DescriptorSpec", "Drive",
           "DriveCentring", "DriveLocalisation", "DriveWriter", "EdgeInfo", "EdgeSpec",
           "FrameDecision", "GnssModel", "GroundTruth", "HMMConfig", "IngestResult",
           "LaggedLocalizer", "LocaliseMany", "Localizer", "MapConfig", "MapService",
           "PreparedDrive", "RemoveResult", "RepairReport", "SequenceRecord", "SprintMap",
           "SprintMapError", "Timing", "Trace", "TraceRecorder", "Traversal", "UnmergeResult",
           "VprDataset", "describe_encoded", "drive_names", "drive_positions", "gnss_fixes",
           "onnx_params", "own_positions", "read_trace", "simulate_fixes", "validate_lag"]
__version__ = "0.1.0"


__getattr__, __dir__ = lazy_names(__name__, {**_USER, **_DOORS})
