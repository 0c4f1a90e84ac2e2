"""Image front end: descriptors, frame sources, data sets on disk and their ground truth.

Public API (see ``docs/frontend.md``):

- :class:`DescriptorSpec` -- the paper's HoG (``"hog"``) or a SeqSLAM-style patch-normalised
  thumbnail (``"patchnorm"``); ``describe`` / ``describe_batch``.
- :func:`open_source` -- a directory of images, a video or a ``.npy``, streamed as descriptor
  batches decoded and described in parallel.
- :func:`read_positions` -- ``frame,x,y[,heading_deg]`` CSV files.
- :class:`Dataset`, :class:`GroundTruth`, :class:`GroundTruthSpec` -- multi-traversal data sets
  and the rule that says whether a retrieved frame is the same place.
"""

from sprint_map.frontend.dataset import Dataset, Traversal
from sprint_map.frontend.descriptors import DESCRIPTOR_KINDS, DescriptorSpec
from sprint_map.frontend.groundtruth import GroundTruth, GroundTruthSpec
from sprint_map.frontend.imagefiles import IMAGE_EXTENSIONS, VIDEO_EXTENSIONS, natural_key
from sprint_map.frontend.positions import read_positions
from sprint_map.frontend.sources import FrameSource, ProgressCallback, open_source

__all__ = [
    "DESCRIPTOR_KINDS",
    "IMAGE_EXTENSIONS",
    "VIDEO_EXTENSIONS",
    "Dataset",
    "DescriptorSpec",
    "FrameSource",
    "GroundTruth",
    "GroundTruthSpec",
    "ProgressCallback",
    "Traversal",
    "natural_key",
    "open_source",
    "read_positions",
]
