"""The map's frozen configuration, stored in its meta record at creation.

The storage layer reads its own fields of it (:class:`sprint_map.storage.store_config.
StoreConfig`, which also checks them); the rest (descriptor, merge rule, HMM) is decoded here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

from sprint_map.frontend.descriptors import DescriptorSpec
from sprint_map.hmm.config import HMMConfig
from sprint_map.merge.rule import MergeRule
from sprint_map.storage.store_config import (
    INDEX_TYPES,
    READABLE_SCHEMA_VERSIONS,
    SCHEMA_VERSION,
    StoreConfig,
)
from sprint_map.util import dataclass_dict

__all__ = ["DESCRIPTOR_KINDS", "INDEX_TYPES", "READABLE_SCHEMA_VERSIONS", "SCHEMA_VERSION",
           "HMMConfig", "MapConfig"]

#: "precomputed": descriptors are given as arrays (.npy); otherwise the front end's kinds.
DESCRIPTOR_KINDS = ("precomputed", "hog", "patchnorm")


@dataclass(frozen=True)
class MapConfig:
    """How a map is built and queried.

    Parameters
    ----------
    dim : int
        Descriptor dimension; every sequence added must match it.
    descriptor : str
        Which descriptor the map holds: ``"precomputed"`` (given as arrays), ``"hog"`` (the
        paper's: 64x64 grayscale HoG, 1764 dims) or ``"patchnorm"`` (SeqSLAM-style).
    descriptor_params : dict
        Parameters of the descriptor kind (see :class:`sprint_map.frontend.descriptors.DescriptorSpec`).
    shard_rows : int
        Rows per descriptor shard file; a shard is sealed (never written again) once full.
    index_type : str
        Retrieval index (see :mod:`sprint_map.storage.index.map_index`): ``"flat"`` (exact L2
        through ``IndexIDMap2(IndexFlatL2)``), ``"ivf-pq"`` / ``"ivf-sq8"`` (segmented FAISS
        IVF with PQ / 8-bit SQ codes, optionally after PCA, candidates re-ranked exactly from
        the shards) or ``"auto"`` (flat while the map is small, ``ivf-pq`` from
        ``index_auto_vertices``). Maps created before the approximate indexes say ``"flat"``.
    index_nlist : int
        IVF lists (coarse centroids) of the approximate indexes.
    index_nprobe : int
        IVF lists scanned per query (at most ``index_nlist``).
    index_pq_m : int
        PQ sub-quantizers (8 bits each; must divide the indexed dimension); 0 picks the
        largest divisor with at least 8 dimensions per sub-quantizer (16 for 128).
    index_pca_dim : int
        Descriptors longer than this are reduced by a PCA trained with the quantizer
        (0: never reduce).
    index_rerank : int
        Candidates re-ranked with exact distances from the shards per query (at least k).
    index_segment_rows : int
        Vertices per sealed index segment; newer vertices (the tail) are searched exactly.
    index_merge_factor : int
        This many sealed segments of one size are merged into one (tiered, like an LSM tree).
    index_auto_vertices : int
        ``auto`` switches to the approximate index once ``vertices * dim`` reaches this many
        128-dimensional vertices' worth (200k at dim 128, ~14.5k at dim 1764).
    index_train_sample : int
        Vertices sampled (seeded, from the whole map) to train PCA and the quantizer.
    index_persist_every : int
        A writer persists the index once the vertices added since the last persisted file reach
        this many and ``index_persist_growth`` times that file's size; it also persists on close.
        The index is a cache, so this only bounds catch-up work after a crash.
    index_persist_growth : float
        Geometric persist interval: a flat index file is rewritten whole, so waiting for the map
        to grow by this fraction keeps total index writes linear in the map size (1.0: persist
        at 2x, 4x, ...). 0 persists every ``index_persist_every`` vertices.
    initial_map_size : int
        LMDB map size at creation in bytes (sparse file; it doubles on demand).
    learn_every : int
        The writer learns a descriptor projection from the map's merged edges again after this
        many new edges (0, the default: only ``index --learn``;
        :mod:`sprint_map.storage.learning`).
    learn_dim : int
        Dimensions the learned projection keeps.
    learn_min_pairs : int
        Fewest merged pairs a projection is learned from (fewer: the plain descriptor).
    merge_threshold : float
        Minimum place probability for a localisation decision to become an edge on merge
        (:mod:`sprint_map.merge.rule`).
    merge_max_novel : float
        A decision whose probability of being an unmapped place exceeds this is not merged.
    merge_window : int
        Temporal consistency: how many frames either side of a decision are looked at.
    merge_min_agree : int
        How many of those neighbours must be matched along the same sequence for the decision
        to be merged (0 disables the check).
    merge_max_rate : float
        Images of the matched sequence a neighbour may advance per frame and still agree.
    merge_min_run : int
        A merged decision lies on a run of at least this many frames matched one after the
        other along the same sequence (0 or 1 disables the check).
    merge_min_advance : float
        The images of such a run advance by at least this many per frame, first frame to
        last (a match stuck on one image while the drive moves on is not merged).
    merge_dist_quantile : float
        A merged decision's frame is at most as far from the map (best-hit distance) as this
        quantile of the distances of the drive's frames that pass every other test (0
        disables the check).
    merge_max_contrast : float
        A merged decision's run stands out from the rest of the map: the median contrast of
        its frames (best hit inside the decided place over best hit elsewhere, smoothed
        decisions) is at most this (0 disables the check).
    merge_verify_inliers : int
        Geometric verification of the runs the lookalike tests refuse, where the drive and
        the map keep thumbnails (``ingest --thumbnails``): a stretch whose sampled frames share
        at least this many inliers (median) with their matched map images is merged
        (:mod:`sprint_map.merge.verification`; unrelated images share 14-20). 0 disables it.
    merge_both_ways : bool
        Store each merge edge in both directions (query -> map and map -> query), so belief can
        later cross between the two drives either way. The paper keeps one direction.
    hmm : HMMConfig
        Parameters of the place-recognition HMM.
    """

    dim: int
    descriptor: str = "precomputed"
    descriptor_params: dict[str, Any] = field(default_factory=dict)
    shard_rows: int = 65536
    index_type: str = "auto"
    index_nlist: int = 1024
    index_nprobe: int = 16
    index_pq_m: int = 0
    index_pca_dim: int = 128
    index_rerank: int = 100
    index_segment_rows: int = 16384
    index_merge_factor: int = 8
    index_auto_vertices: int = 200_000
    index_train_sample: int = 65536
    index_persist_every: int = 200_000
    index_persist_growth: float = 1.0
    initial_map_size: int = 1 << 30
    learn_every: int = 0
    learn_dim: int = 256
    learn_min_pairs: int = 500
    merge_threshold: float = 0.5
    merge_max_novel: float = 0.2
    merge_window: int = 3
    merge_min_agree: int = 0
    merge_max_rate: float = 3.0
    merge_min_run: int = 20
    merge_dist_quantile: float = 0.0
    merge_min_advance: float = 0.3
    merge_max_contrast: float = 0.95
    merge_verify_inliers: int = 35
    merge_both_ways: bool = True
    hmm: HMMConfig = field(default_factory=HMMConfig)

    def __post_init__(self) -> None:
        if not isinstance(self.dim, int) or self.dim < 1:
            raise ValueError("dim must be a positive integer")
        if self.descriptor not in DESCRIPTOR_KINDS:
            raise ValueError(f"descriptor must be one of {', '.join(DESCRIPTOR_KINDS)}")
        spec = self.descriptor_spec()
        if spec is not None and spec.dim != self.dim:
            raise ValueError(f"{self.descriptor} descriptors have {spec.dim} dimensions, not {self.dim}")
        # The storage fields are checked by the storage layer's view of them.
        _ = self.storage
        if not 0 <= self.merge_threshold <= 1:
            raise ValueError("merge_threshold must be in [0, 1]")
        if not 0 <= self.merge_max_novel <= 1:
            raise ValueError("merge_max_novel must be in [0, 1]")
        if not isinstance(self.merge_window, int) or self.merge_window < 0:
            raise ValueError("merge_window must be an integer >= 0")
        if not isinstance(self.merge_min_agree, int) or not 0 <= self.merge_min_agree <= 2 * self.merge_window:
            raise ValueError("merge_min_agree must be an integer in [0, 2 * merge_window]")
        if not self.merge_max_rate > 0:
            raise ValueError("merge_max_rate must be > 0")
        if not isinstance(self.merge_min_run, int) or self.merge_min_run < 0:
            raise ValueError("merge_min_run must be an integer >= 0")
        if not 0 <= self.merge_dist_quantile <= 1:
            raise ValueError("merge_dist_quantile must be in [0, 1]")
        if not 0 <= self.merge_min_advance <= self.merge_max_rate:
            raise ValueError("merge_min_advance must be in [0, merge_max_rate]")
        if not 0 <= self.merge_max_contrast < math.inf:
            raise ValueError("merge_max_contrast must be a finite number >= 0")
        if not isinstance(self.merge_verify_inliers, int) or self.merge_verify_inliers < 0:
            raise ValueError("merge_verify_inliers must be an integer >= 0")

    @property
    def merge_rule(self) -> MergeRule:
        """The merge rule these fields define (:mod:`sprint_map.merge.rule`)."""
        return MergeRule(self.merge_threshold, self.merge_max_novel, self.merge_window,
                         self.merge_min_agree, self.merge_max_rate, self.merge_min_run,
                         self.merge_dist_quantile, self.merge_min_advance,
                         self.merge_max_contrast)

    @property
    def storage(self) -> StoreConfig:
        """The fields the storage layer reads (:class:`~sprint_map.storage.store_config.
        StoreConfig`); ValueError if one is out of range. O(fields)."""
        return StoreConfig(**{f.name: getattr(self, f.name) for f in fields(StoreConfig)})

    @property
    def index_dim(self) -> int:
        """Dimension the approximate index quantizes: after PCA when ``dim > index_pca_dim``."""
        return self.storage.index_dim

    @property
    def pq_m(self) -> int:
        """PQ sub-quantizers: ``index_pq_m``, or the largest divisor of :attr:`index_dim` with
        at least 8 dimensions each (1 if none)."""
        return self.storage.pq_m

    def descriptor_spec(self) -> DescriptorSpec | None:
        """The front end's descriptor for images and video, or None for precomputed ones."""
        if self.descriptor == "precomputed":
            return None
        return DescriptorSpec(self.descriptor, dict(self.descriptor_params))

    @classmethod
    def for_descriptor(cls, kind: str, params: dict[str, Any] | None = None, **options: Any
                       ) -> MapConfig:
        """A config for descriptor ``kind``, its dimension derived from the kind and params."""
        spec = DescriptorSpec(kind, dict(params or {}))
        return cls(dim=spec.dim, descriptor=kind, descriptor_params=dict(spec.params), **options)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MapConfig:
        """Build from a dict (as stored in the map's meta record)."""
        return dataclass_dict.from_dict(cls, data)

    def to_dict(self) -> dict[str, Any]:
        """Return a JSON-ready dict."""
        return dataclass_dict.to_dict(self)
