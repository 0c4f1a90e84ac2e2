"""The map's frozen configuration, stored in its meta record at creation."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from sprint_map import dataclass_dict
from sprint_map.hmm.config import HMMConfig

#: On-disk schema version written into every map; maps of another version are refused.
SCHEMA_VERSION = 1

DESCRIPTOR_KINDS = ("precomputed",)


@dataclass(frozen=True)
class MapConfig:
    """How a map is built and queried.

    Parameters
    ----------
    dim : int
        Descriptor dimension; every sequence added must match it.
    descriptor : str
        Which descriptor the map holds (``"precomputed"``: given as arrays).
    shard_rows : int
        Rows per descriptor shard file; a shard is sealed (never written again) once full.
    index_type : str
        FAISS index kind (``"flat"``: exact L2 through ``IndexIDMap2(IndexFlatL2)``).
    index_persist_every : int
        A writer persists the index after this many vertices were added since the last persist
        (it also persists on close); the index is a cache, so this only bounds catch-up work.
    initial_map_size : int
        LMDB map size at creation in bytes (sparse file; it doubles on demand).
    merge_threshold : float
        Minimum decision probability for a localisation decision to become an edge on merge.
    hmm : HMMConfig
        Parameters of the place-recognition HMM.
    """

    dim: int
    descriptor: str = "precomputed"
    shard_rows: int = 65536
    index_type: str = "flat"
    index_persist_every: int = 200_000
    initial_map_size: int = 1 << 30
    merge_threshold: float = 0.5
    hmm: HMMConfig = field(default_factory=HMMConfig)

    def __post_init__(self) -> None:
        if not isinstance(self.dim, int) or self.dim < 1:
            raise ValueError("dim must be a positive integer")
        if self.descriptor not in DESCRIPTOR_KINDS:
            raise ValueError(f"descriptor must be one of {', '.join(DESCRIPTOR_KINDS)}")
        if self.shard_rows < 1:
            raise ValueError("shard_rows must be >= 1")
        if self.index_type != "flat":
            raise ValueError("index_type must be 'flat'")
        if self.index_persist_every < 1:
            raise ValueError("index_persist_every must be >= 1")
        if self.initial_map_size < 1 << 20:
            raise ValueError("initial_map_size must be at least 1 MiB")
        if not 0 <= self.merge_threshold <= 1:
            raise ValueError("merge_threshold must be in [0, 1]")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MapConfig:
        """Build from a dict (as stored in the map's meta record)."""
        return dataclass_dict.from_dict(cls, data)

    def to_dict(self) -> dict[str, Any]:
        """Return a JSON-ready dict."""
        return dataclass_dict.to_dict(self)
