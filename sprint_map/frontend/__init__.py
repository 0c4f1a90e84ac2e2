"""Image front end: descriptors, frame sources, data sets on disk and their ground truth.

Public API (see ``docs/frontend.md``, "Front end"):

- :class:`DescriptorSpec` -- the paper's HoG (``"hog"``), a SeqSLAM-style patch-normalised
  thumbnail (``"patchnorm"``) or a user's ONNX model (``"onnx"``); ``describe_batch``.
- :func:`open_source` -- a directory of images, a video, a ``.npy`` or a ROS bag / MCAP
  (:class:`BagOptions`), streamed as descriptor batches decoded and described in parallel.
- :func:`read_positions` -- ``frame,x,y`` or ``frame,lat,lon`` (``[,heading_deg][,sigma_m]``)
  CSV files, as :class:`Positions`.
- :class:`VprDataset` -- the VPR benchmarks' ``database/`` + ``queries/`` layout.
- :class:`Dataset`, :class:`GroundTruth`, :class:`GroundTruthSpec` -- multi-traversal data sets
  and the rule that says whether a retrieved frame is the same place.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from sprint_map.util.lazy import lazy_names

if TYPE_CHECKING:
    from sprint_map.frontend.bags import BagOptions
    from sprint_map.frontend.dataset import Dataset, Traversal
    from sprint_map.frontend.descriptors import DESCRIPTOR_KINDS, DescriptorSpec
    from sprint_map.frontend.groundtruth import GroundTruth, GroundTruthSpec
    from sprint_map.frontend.imagefiles import IMAGE_EXTENSIONS, VIDEO_EXTENSIONS, natural_key
    from sprint_map.frontend.positions import Positions, read_positions
    from sprint_map.frontend.sources import FrameSource, ProgressCallback, open_source
    from sprint_map.frontend.vpr import VprDataset

#: Each public name and the module that defines it: imported on first use (PEP 562), so a
#: module that needs only descriptor specs does not load data sets (scipy) or OpenCV.
_LAZY = {
    "Dataset": "dataset", "Traversal": "dataset",
    "DESCRIPTOR_KINDS": "descriptors", "DescriptorSpec": "descriptors",
    "GroundTruth": "groundtruth", "GroundTruthSpec": "groundtruth",
    "IMAGE_EXTENSIONS": "imagefiles", "VIDEO_EXTENSIONS": "imagefiles",
    "natural_key": "imagefiles", "read_positions": "positions", "Positions": "positions",
    "BagOptions": "bags", "VprDataset": "vpr",
    "FrameSource": "sources", "ProgressCallback": "sources", "open_source": "sources",
}


__getattr__, __dir__ = lazy_names(__name__, {name: f"{__name__}.{module}"
                                             for name, module in _LAZY.items()})


__all__ = [
    "BagOptions",
    "DESCRIPTOR_KINDS",
    "IMAGE_EXTENSIONS",
    "VIDEO_EXTENSIONS",
    "Dataset",
    "DescriptorSpec",
    "FrameSource",
    "GroundTruth",
    "GroundTruthSpec",
    "Positions",
    "ProgressCallback",
    "Traversal",
    "VprDataset",
    "natural_key",
    "open_source",
    "read_positions",
]
