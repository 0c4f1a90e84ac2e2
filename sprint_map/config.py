"""The map's frozen configuration, stored in its meta record at creation."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from sprint_map import dataclass_dict
from sprint_map.frontend.descriptors import DescriptorSpec
from sprint_map.hmm.config import HMMConfig

#: On-disk schema version written into every map; maps of another version are refused.
#: 2 added removed vertex ranges (``remove``) and generation directories (``compact``); a
#: schema-1 map is read as it is and upgraded by the first writer's open.
SCHEMA_VERSION = 2
#: Versions this code opens.
READABLE_SCHEMA_VERSIONS = (1, 2)

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
        FAISS index kind (``"flat"``: exact L2 through ``IndexIDMap2(IndexFlatL2)``).
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
    merge_threshold : float
        Minimum decision probability for a localisation decision to become an edge on merge.
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
    index_type: str = "flat"
    index_persist_every: int = 200_000
    index_persist_growth: float = 1.0
    initial_map_size: int = 1 << 30
    merge_threshold: float = 0.5
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
        if self.shard_rows < 1:
            raise ValueError("shard_rows must be >= 1")
        if self.index_type != "flat":
            raise ValueError("index_type must be 'flat'")
        if self.index_persist_every < 1:
            raise ValueError("index_persist_every must be >= 1")
        if not self.index_persist_growth >= 0:
            raise ValueError("index_persist_growth must be >= 0")
        if self.initial_map_size < 1 << 20:
            raise ValueError("initial_map_size must be at least 1 MiB")
        if not 0 <= self.merge_threshold <= 1:
            raise ValueError("merge_threshold must be in [0, 1]")

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
