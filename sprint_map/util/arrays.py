"""The array types of sprint-map, for annotations (``numpy.typing``; mypy checks them).

Descriptors are float32 rows everywhere they are stored, searched or streamed; vertex ids and
indices are int64; beliefs and positions float64. Annotate with these names rather than a bare
``np.ndarray`` (whose dtype is ``Any``), so that mypy catches, say, float64 rows handed to the
store.
"""

from __future__ import annotations

from typing import Any, TypeAlias

import numpy as np
from numpy.typing import NDArray

__all__ = [
    "BoolArray",
    "Descriptors",
    "DescriptorsLike",
    "Float32Array",
    "Float64Array",
    "Image",
    "Int32Array",
    "Int64Array",
    "IntArray",
    "SearchResult",
    "UInt8Array",
]

#: ``(n, dim)`` descriptor rows (one per frame or vertex), float32: as the shards store them,
#: FAISS searches them and frame sources yield them. Also a single row ``(dim,)``.
Descriptors: TypeAlias = NDArray[np.float32]
#: Descriptor rows as a caller may give them (any float dtype): validated and converted to
#: float32 (:data:`Descriptors`) before they are stored or searched.
DescriptorsLike: TypeAlias = NDArray[np.floating[Any]]
#: Any float32 array (squared L2 distances of a search, likelihoods).
Float32Array: TypeAlias = NDArray[np.float32]
#: Any float64 array (beliefs, positions ``(n, 2..4)``, probabilities, metrics).
Float64Array: TypeAlias = NDArray[np.float64]
#: int64 arrays: vertex ids (``-1`` pads a search's missing hits), slots, sequence ids.
Int64Array: TypeAlias = NDArray[np.int64]
#: int32 arrays (compact component-local indices where memory matters).
Int32Array: TypeAlias = NDArray[np.int32]
#: Integer arrays of any width (what ``np.searchsorted`` and friends return: ``intp``).
IntArray: TypeAlias = NDArray[np.integer[Any]]
#: Boolean masks.
BoolArray: TypeAlias = NDArray[np.bool_]
#: uint8 arrays (encoded bytes, thumbnails).
UInt8Array: TypeAlias = NDArray[np.uint8]
#: A decoded image: ``(h, w)`` gray or ``(h, w, 3|4)`` BGR(A), uint8 in practice (uint16 is
#: accepted on input); typed as OpenCV's own stubs type the images it returns.
Image: TypeAlias = NDArray[np.integer[Any] | np.floating[Any]]
#: What a k-NN search returns: ``(distances, ids)``, each ``(n_queries, k)``: squared L2
#: distances (float32) and vertex ids (int64; ``-1`` with an infinite distance pads a row
#: with fewer than ``k`` hits).
SearchResult: TypeAlias = tuple[Float32Array, Int64Array]
