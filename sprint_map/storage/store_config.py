"""What the storage layer reads of a map's configuration, and the on-disk schema versions.

A map stores its whole configuration (:class:`sprint_map.config.MapConfig`, HMM parameters
included) as one JSON object in its meta record. The storage layer needs only part of it: the
descriptor dimension, the shard size, the retrieval index's parameters and the LMDB size.
:class:`StoreConfig` is that part, read from the stored record by picking its keys; the rest
(descriptor kind, merge rule, HMM) is the facade's to decode. So storage knows nothing of HMMs
or images: it stores the record as given and checks only its own fields.

``MapConfig.store`` is a :class:`StoreOptions`; a record written before the config was nested
holds the same fields at its top level, which :meth:`StoreConfig.from_record` reads too.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields
from typing import Any, Protocol, TypeVar

from sprint_map.errors import ConfigError, MapCorruptError, SchemaVersionError, SprintMapError
from sprint_map.util import dataclass_dict

__all__ = ["INDEX_TYPES", "MIN_TRAIN", "READABLE_SCHEMA_VERSIONS", "SCHEMA_VERSION", "ConfigRecord",
           "StoreConfig", "StoreOptions", "decode_stored_config"]

_Config = TypeVar("_Config")

#: On-disk schema version written into every map; maps of another version are refused.
#: 2 added removed vertex ranges (``remove``) and generation directories (``compact``); a
#: schema-1 map is read as it is and upgraded by the first writer's open.
SCHEMA_VERSION = 2
#: Versions this code opens.
READABLE_SCHEMA_VERSIONS = (1, 2)

#: Retrieval index kinds (``index_type``).
INDEX_TYPES = ("flat", "ivf-pq", "ivf-sq8", "auto")
#: Fewest vertices an approximate index is trained on (8-bit PQ codebooks have 256 centroids).
MIN_TRAIN = 256


class ConfigRecord(Protocol):
    """A map's whole configuration as handed to :meth:`MapStore.create
    <sprint_map.storage.store.MapStore.create>` (``MapConfig`` is one): stored as the JSON
    object :meth:`to_dict` returns."""

    def to_dict(self) -> dict[str, Any]: ...


@dataclass(frozen=True)
class StoreOptions:
    """How a map stores and indexes its rows: ``MapConfig.store``. Raises ``ValueError`` for a
    value out of range.

    Each field is described by the comment above it.
    """

    #: Rows per descriptor shard file; a shard is sealed (never written again) once full.
    shard_rows: int = 65536
    #: Retrieval index (:mod:`sprint_map.storage.index.map_index`): ``"flat"`` (exact L2),
    #: ``"ivf-pq"`` / ``"ivf-sq8"`` (segmented FAISS IVF with PQ / 8-bit SQ codes, optionally
    #: after PCA, candidates re-ranked exactly from the shards) or ``"auto"`` (flat while the map
    #: is small, ``ivf-pq`` from ``index_auto_vertices``).
    index_type: str = "auto"
    #: IVF lists (coarse centroids); 0 follows the map's size: about the square root of the
    #: vertices the model serves before it is trained again (``index_retrain_growth`` times
    #: those it is trained on), so a list's length grows with the square root of the map, not
    #: with the map (:func:`~sprint_map.storage.index.model.list_count`).
    index_nlist: int = 0
    #: Lists scanned per query (all of them where there are fewer).
    index_nprobe: int = 24
    #: PQ sub-quantizers (must divide the indexed dimension); 0 picks the largest divisor with at
    #: least 8 dimensions per sub-quantizer.
    index_pq_m: int = 0
    #: Descriptors longer than this are reduced by a PCA trained with the quantizer (0: never).
    index_pca_dim: int = 128
    #: Candidates re-ranked with exact distances from the shards per query (at least k).
    index_rerank: int = 100
    #: Vertices per sealed index segment; ``index_merge_factor`` sealed segments of one size are
    #: merged.
    index_segment_rows: int = 16384
    index_merge_factor: int = 8
    #: Merges stop at segments of this many vertices (0: no limit), so that the retrieval
    #: shards of a fleet can own ranges of whole segments (:mod:`sprint_map.fleet.shards`).
    index_segment_max_rows: int = 1 << 20
    #: ``auto`` switches to the approximate index at this many 128-dimensional vertices' worth.
    index_auto_vertices: int = 200_000
    #: Vertices sampled (seeded) to train PCA and the quantizer.
    index_train_sample: int = 65536
    #: The writer trains the approximate index again (a new generation, like ``index
    #: --train``) once the map holds this many times the vertices its model was trained on,
    #: so that its lists and codebooks follow the map as it grows (0: never).
    index_retrain_growth: float = 4.0
    #: A writer persists the index once this many vertices were added since the last file and the
    #: map grew by ``index_persist_growth`` times that file's size (0: every time).
    index_persist_every: int = 200_000
    index_persist_growth: float = 1.0
    #: LMDB map size at creation in bytes (sparse file; it doubles on demand).
    initial_map_size: int = 1 << 30
    #: The writer learns a descriptor projection from the map's merged edges again after this
    #: many new edges (0: only ``index --learn``; :mod:`sprint_map.storage.learning`).
    learn_every: int = 0
    #: Dimensions the learned projection keeps.
    learn_dim: int = 256
    #: Fewest merged pairs a projection is learned from (fewer: the plain descriptor).
    learn_min_pairs: int = 500

    def __post_init__(self) -> None:
        if self.shard_rows < 1:
            raise ValueError("shard_rows must be >= 1")
        if self.index_type not in INDEX_TYPES:
            raise ValueError(f"index_type must be one of {', '.join(INDEX_TYPES)}")
        for name in ("index_nprobe", "index_rerank", "index_segment_rows"):
            if not isinstance(getattr(self, name), int) or getattr(self, name) < 1:
                raise ValueError(f"{name} must be a positive integer")
        if not isinstance(self.index_nlist, int) or self.index_nlist < 0:
            raise ValueError("index_nlist must be an integer >= 0 (0: follow the map's size)")
        if self.index_pca_dim < 0 or self.index_pq_m < 0:
            raise ValueError("index_pca_dim and index_pq_m must be >= 0")
        if self.index_merge_factor < 2:
            raise ValueError("index_merge_factor must be >= 2")
        if not isinstance(self.index_segment_max_rows, int) or not (
                self.index_segment_max_rows == 0
                or self.index_segment_max_rows >= self.index_segment_rows):
            raise ValueError("index_segment_max_rows must be 0 (no limit) or >= "
                             "index_segment_rows")
        if self.index_auto_vertices < 1:
            raise ValueError("index_auto_vertices must be >= 1")
        if self.index_train_sample < max(self.index_nlist, MIN_TRAIN):
            raise ValueError(f"index_train_sample must be >= index_nlist and >= {MIN_TRAIN}")
        if not (self.index_retrain_growth == 0 or self.index_retrain_growth > 1):
            raise ValueError("index_retrain_growth must be 0 (never) or > 1")
        if self.index_persist_every < 1:
            raise ValueError("index_persist_every must be >= 1")
        if not self.index_persist_growth >= 0:
            raise ValueError("index_persist_growth must be >= 0")
        if self.initial_map_size < 1 << 20:
            raise ValueError("initial_map_size must be at least 1 MiB")
        for name in ("learn_every", "learn_min_pairs"):
            if not isinstance(getattr(self, name), int) or getattr(self, name) < 0:
                raise ValueError(f"{name} must be an integer >= 0")
        if not isinstance(self.learn_dim, int) or self.learn_dim < 1:
            raise ValueError("learn_dim must be a positive integer")


@dataclass(frozen=True)
class StoreConfig(StoreOptions):
    """The storage layer's view of a map's configuration: its :class:`StoreOptions` and the
    descriptor dimension. Raises ``ValueError`` for a value out of range."""

    dim: int = field(kw_only=True)

    def __post_init__(self) -> None:
        if not isinstance(self.dim, int) or self.dim < 1:
            raise ValueError("dim must be a positive integer")
        super().__post_init__()
        if self.index_pq_m and self.index_dim % self.index_pq_m:
            raise ValueError(f"index_pq_m ({self.index_pq_m}) must divide the indexed "
                             f"dimension ({self.index_dim})")

    @property
    def options(self) -> StoreOptions:
        """The options alone (what ``MapConfig.store`` holds)."""
        return StoreOptions(**{f.name: getattr(self, f.name) for f in fields(StoreOptions)})

    @property
    def index_dim(self) -> int:
        """Dimension the approximate index quantizes: after PCA when ``dim > index_pca_dim``."""
        return self.index_pca_dim if 0 < self.index_pca_dim < self.dim else self.dim

    @property
    def pq_m(self) -> int:
        """PQ sub-quantizers: ``index_pq_m``, or the largest divisor of :attr:`index_dim` with
        at least 8 dimensions each (1 if none)."""
        if self.index_pq_m:
            return self.index_pq_m
        d = self.index_dim
        return max([m for m in range(1, d // 8 + 1) if d % m == 0] or [1])

    @classmethod
    def from_record(cls, record: Mapping[str, Any]) -> StoreConfig:
        """The storage part of a stored configuration record: ``dim`` and the ``store``
        object, or, in a record written before the config was nested, the same keys at the
        top level (other keys are not storage's; a missing one takes its default). O(fields).

        Raises
        ------
        ConfigError
            A storage field of the wrong type or out of range, named as ``MapConfig`` names it.
        """
        names = {f.name for f in fields(cls)}
        nested = record.get("store")
        flat = {k: v for k, v in record.items() if k in names}
        if not isinstance(nested, Mapping):
            return dataclass_dict.from_dict(cls, flat, where="MapConfig")
        # a flat key overrides the nested one, as MapConfig.from_dict reads it
        return dataclass_dict.from_dict(cls, {**nested, **flat}, where="MapConfig.store")


def decode_stored_config(decode: Callable[[dict[str, Any]], _Config], data: Any) -> _Config:
    """``decode(data)`` of a map's stored config record (decoded JSON), or MapCorruptError if
    it is not a valid config: not an object, or values the config refuses (of the wrong type
    or out of range: a map is only ever created with a valid one). Options no field has are a
    later release's (SchemaVersionError, naming them), not damage. The store decodes its
    fields with it (:class:`StoreConfig`), the facade the whole config. O(fields)."""
    if not isinstance(data, dict):
        raise MapCorruptError("corrupt map record config: not a JSON object")
    try:
        return decode(data)
    except ConfigError as exc:
        if exc.unknown:  # well-formed options of a later release, not damage
            raise SchemaVersionError(
                f"the map's config has option(s) this sprint-map does not know "
                f"({', '.join(exc.unknown)}): it was made by a newer sprint-map; upgrade to "
                f"open it") from exc
        raise MapCorruptError(f"corrupt map record config: {exc}") from exc
    except SprintMapError:
        raise
    except (ValueError, TypeError, KeyError, AttributeError, RecursionError) as exc:
        raise MapCorruptError(f"corrupt map record config: {exc}") from exc
