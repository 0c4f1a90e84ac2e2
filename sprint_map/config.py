"""The map's frozen configuration, stored in its meta record at creation.

The storage layer reads its own fields of it (:class:`sprint_map.storage.store_config.
StoreConfig`, which also checks them); the rest (descriptor, merge rule, HMM) is decoded here.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import Any

from sprint_map.frontend.centring import Centring
from sprint_map.frontend.descriptors import DescriptorSpec
from sprint_map.hmm.config import HMMConfig
from sprint_map.localize.gnss import GnssConfig
from sprint_map.merge.admission import Admission
from sprint_map.merge.rule import MergeRule
from sprint_map.storage.store_config import (
    INDEX_TYPES,
    READABLE_SCHEMA_VERSIONS,
    SCHEMA_VERSION,
    StoreConfig,
    StoreOptions,
)
from sprint_map.util import dataclass_dict

__all__ = ["DESCRIPTOR_KINDS", "INDEX_TYPES", "READABLE_SCHEMA_VERSIONS", "SCHEMA_VERSION",
           "Admission", "GnssConfig", "HMMConfig", "MapConfig", "MergeRule", "StoreOptions", "nest_flat_keys"]

#: "precomputed": descriptors are given as arrays (.npy); otherwise the front end's kinds.
DESCRIPTOR_KINDS = ("precomputed", "hog", "patchnorm", "onnx")


@dataclass(frozen=True)
class MapConfig:
    """How a map is built and queried: the descriptor, and one part per layer.

    Parameters
    ----------
    dim : int
        Descriptor dimension; every sequence added must match it.
    descriptor : str
        Which descriptor the map holds: ``"precomputed"`` (given as arrays), ``"hog"`` (the
        paper's: 64x64 grayscale HoG, 1764 dims), ``"patchnorm"`` (SeqSLAM-style) or
        ``"onnx"`` (a user's model: :mod:`sprint_map.frontend.onnx_model`).
    descriptor_params : dict
        Parameters of the descriptor kind (:class:`sprint_map.frontend.descriptors.DescriptorSpec`).
    store, hmm, merge : StoreOptions, HMMConfig, MergeRule
        How rows are stored and indexed, the place-recognition HMM, which decisions become edges
        (:mod:`sprint_map.storage.store_config`, :mod:`sprint_map.hmm.config`,
        :mod:`sprint_map.merge.rule`).
    gnss : GnssConfig
        How GNSS fixes weigh localisation and merging (:mod:`sprint_map.localize.gnss`).
    admission : Admission
        Which frames are stored: all, or what the map lacks (:mod:`sprint_map.merge.admission`).
    centring : Centring
        Descriptors as given (the default) or centred on their drive's running mean
        (:mod:`sprint_map.frontend.centring`). A stored map lacking a part takes its default.
    """

    dim: int
    descriptor: str = "precomputed"
    descriptor_params: dict[str, Any] = field(default_factory=dict)
    store: StoreOptions = field(default_factory=StoreOptions)
    hmm: HMMConfig = field(default_factory=HMMConfig)
    merge: MergeRule = field(default_factory=MergeRule)
    gnss: GnssConfig = field(default_factory=GnssConfig)
    admission: Admission = field(default_factory=Admission)
    centring: Centring = field(default_factory=Centring)

    def __post_init__(self) -> None:
        if not isinstance(self.dim, int) or self.dim < 1:
            raise ValueError("dim must be a positive integer")
        if self.descriptor not in DESCRIPTOR_KINDS:
            raise ValueError(f"descriptor must be one of {', '.join(DESCRIPTOR_KINDS)}")
        spec = self.descriptor_spec()
        if spec is not None and spec.dim != self.dim:
            raise ValueError(f"{self.descriptor} descriptors have {spec.dim} dimensions, not {self.dim}")
        _ = self.storage  # the checks that need the dimension

    @property
    def storage(self) -> StoreConfig:
        """The storage layer's view (:class:`~sprint_map.storage.store_config.StoreConfig`):
        :attr:`store` and :attr:`dim`; ValueError if they disagree. O(fields)."""
        return StoreConfig(dim=self.dim, **{f.name: getattr(self.store, f.name)
                                            for f in fields(StoreOptions)})

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
        """Build from a dict (as stored in the map's meta record), nested or in the flat form
        of maps written before the config was nested; a flat key overrides the same field of
        a nested part."""
        return dataclass_dict.from_dict(cls, nest_flat_keys(data))

    def to_dict(self) -> dict[str, Any]:
        """Return a JSON-ready dict (nested: ``store``, ``hmm``, ``merge``, ``gnss``)."""
        return dataclass_dict.to_dict(self)

    def replace(self, **changes: Any) -> MapConfig:
        """A copy with ``changes``, validated; flat keys (``index_type=...``,
        ``merge_min_run=...``) change the field of their part."""
        return MapConfig.from_dict({**self.to_dict(), **changes})


def nest_flat_keys(data: Any) -> Any:
    """``data`` with the flat keys of a pre-nesting config record moved into their parts:
    storage fields into ``store``, ``merge_<field>`` into ``merge``. O(keys)."""
    if not isinstance(data, dict):
        return data
    store_names = {f.name for f in fields(StoreOptions)}
    merge_names = {f.name for f in fields(MergeRule)}
    out: dict[str, Any] = {}
    store: dict[str, Any] = {}
    merge: dict[str, Any] = {}
    for key, value in data.items():
        if key in store_names:
            store[key] = value
        elif key.startswith("merge_") and key.removeprefix("merge_") in merge_names:
            merge[key.removeprefix("merge_")] = value
        else:
            out[key] = value
    for name, part in (("store", store), ("merge", merge)):
        if part:
            nested = out.get(name, {})
            out[name] = {**nested, **part} if isinstance(nested, dict) else nested
    return out
