"""Every retrieval index kind passes the one contract (``tests/helpers/index_contract.py``)."""

from __future__ import annotations

from sprint_map.storage.index.flat import FlatIndex
from sprint_map.storage.index.model import MIN_TRAIN
from sprint_map.storage.index.segmented import SegmentedIndex
from sprint_map.storage.store_config import StoreConfig
from tests.helpers.index_contract import IndexContract

DIM = 32


class TestFlatIndex(IndexContract):
    index_cls = FlatIndex
    config = StoreConfig(dim=DIM, index_type="flat")


class TestSegmentedIndex(IndexContract):
    """Small segments and quantizer: sealed segments, a merge and a tail on 700 rows."""

    index_cls = SegmentedIndex
    config = StoreConfig(dim=DIM, index_type="ivf-pq", index_nlist=16, index_nprobe=8,
                       index_segment_rows=256, index_merge_factor=3, index_train_sample=2000,
                       index_rerank=50)
    min_rows = MIN_TRAIN
    min_self_recall = 0.95
    min_recall = 0.8


class TestSegmentedSQ8Index(TestSegmentedIndex):
    """The scalar-quantized variant, with a PCA (dim 32 -> 16)."""

    config = StoreConfig(dim=DIM, index_type="ivf-sq8", index_nlist=16, index_nprobe=8,
                       index_pca_dim=16, index_segment_rows=256, index_merge_factor=3,
                       index_train_sample=2000, index_rerank=50)
