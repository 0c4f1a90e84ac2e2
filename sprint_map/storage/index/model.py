"""The trained part of the approximate index: optional PCA and an empty IVF quantizer.

A model is trained once on a seeded sample of the map's descriptors and reused by every index
segment of its generation, so a segment can be encoded without touching the others and segments
of one generation can be searched (and merged) as one IVF index.

Files (in ``index/``, each published atomically, named by generation ``GGGGGG``):

* ``model.GGGGGG.faiss``: the trained, empty ``IndexIVFPQ`` or ``IndexIVFScalarQuantizer``;
* ``pca.GGGGGG.faiss``: the ``PCAMatrix`` (only when ``dim > index_pca_dim``).
"""

from __future__ import annotations

import errno
import math
import os
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sprint_map.errors import MapCorruptError
from sprint_map.storage.index.projection import Projection
from sprint_map.storage.shards import ShardSet
from sprint_map.storage.store_config import MIN_TRAIN, StoreConfig
from sprint_map.util.arrays import Descriptors, Int64Array
from sprint_map.util.atomic import publish

if TYPE_CHECKING:
    import faiss
else:  # imported on first use: commands that only read LMDB never load it
    from sprint_map.util.lazy import faiss

__all__ = ["APPROX_KINDS", "CORES", "KMEANS_ITER", "MIN_LISTS", "MIN_TRAIN", "Model",
           "PCA_SAMPLE", "POINTS_PER_LIST", "RowReader", "SAMPLE_SEED", "TRAIN_SAMPLE_BYTES",
           "cap_threads", "gather_rows", "list_count", "model_name", "pca_name",
           "publish_bytes", "read_faiss", "sample_ids", "serialize", "train_model",
           "train_sample_size", "use_threads"]

#: Training vectors per IVF list the coarse k-means wants at least (FAISS warns below 39).
POINTS_PER_LIST = 39
#: Vectors the PCA is trained on at most (its covariance costs dim^2 per vector).
PCA_SAMPLE = 20000
#: Fewest IVF lists a map's size gives (:func:`list_count`).
MIN_LISTS = 64
#: Descriptor bytes the training sample may hold at most (a sample for many lists of long
#: descriptors is capped here, and with it the lists: :func:`train_sample_size`).
TRAIN_SAMPLE_BYTES = 1 << 29
#: k-means iterations for the coarse quantizer and the PQ codebooks.
KMEANS_ITER = 10
#: Seed of the training sample (with the generation): retraining the same map is reproducible.
SAMPLE_SEED = 20200601

APPROX_KINDS = ("ivf-pq", "ivf-sq8")
#: Threads for training and encoding (searches of one query use one: see ``use_threads``).
CORES = os.cpu_count() or 1


_LOCAL = threading.local()


def use_threads(n_queries: int) -> None:
    """One OpenMP thread for a few queries (latency-bound; threads only add overhead), every
    core for batches, training and encoding (at most the calling thread's
    :func:`cap_threads`)."""
    faiss.omp_set_num_threads(1 if n_queries < 8 else min(CORES, getattr(_LOCAL, "cap", CORES)))


def cap_threads(n: int) -> None:
    """Use at most ``n`` OpenMP threads for the searches of the calling thread from now on
    (e.g. the service's batch searcher, whose other core answers HTTP: a second OpenMP
    thread there waits on a busy core at every barrier)."""
    _LOCAL.cap = max(1, int(n))


def model_name(generation: int) -> str:
    return f"model.{generation:06d}.faiss"


def pca_name(generation: int) -> str:
    return f"pca.{generation:06d}.faiss"


def gather_rows(shards: ShardSet, ids: Int64Array, committed: int) -> Descriptors:
    """Shard rows of ``ids`` (any order, no -1), copied; one memory-map view per shard touched.

    Notes
    -----
    O(len(ids) * dim) copies plus O(shards touched) view look-ups.
    """
    ids = np.asarray(ids, dtype=np.int64)
    out = np.empty((len(ids), shards.dim), dtype=np.float32)
    if not len(ids):
        return out
    shard_of = ids // shards.shard_rows
    for shard in np.unique(shard_of):
        first = int(shard) * shards.shard_rows
        rows = shards.rows(first, min(first + shards.shard_rows, committed), committed)
        sel = np.flatnonzero(shard_of == shard)
        out[sel] = rows[ids[sel] - first]
    return out


class RowReader:
    """Reads scattered shard rows with ``pread`` (one file descriptor per shard, kept open).

    Re-ranking reads a few hundred random rows per query. Through the shards' memory maps each
    of them would fault in (and map into this process, counted in its RSS) the 64 KB the kernel
    maps around a faulting page: at 10M vertices that grew the localiser's RSS by ~2.8 GB of
    page cache in 300 frames and cost ~7 ms per query. ``pread`` copies just the rows.
    """

    def __init__(self) -> None:
        self._fds: dict[int, int] = {}  # shard number -> descriptor, for ``_directory``
        self._directory: Path | None = None

    def rows(self, shards: ShardSet, ids: Int64Array, committed: int) -> Descriptors:
        """Rows of the committed vertex ``ids``. O(len(ids)) reads of one row each."""
        if shards.directory != self._directory:
            self.close()
            self._directory = shards.directory
        out = np.empty((len(ids), shards.dim), dtype=np.float32)
        if not len(ids):
            return out
        view = memoryview(out.data).cast("B")
        size, per_shard, fds = shards.row_bytes, shards.shard_rows, self._fds
        for i, vid in enumerate(np.asarray(ids, dtype=np.int64).tolist()):
            if not 0 <= vid < committed:
                raise IndexError(f"vertex {vid} outside 0..{committed}")
            shard, row = divmod(vid, per_shard)
            fd = fds.get(shard)
            if fd is None:
                try:
                    fd = fds[shard] = os.open(shards.path(shard), os.O_RDONLY)
                except FileNotFoundError:
                    raise MapCorruptError(f"shard file {shards.path(shard).name} is missing: "
                                          "committed descriptors are lost") from None
            if os.preadv(fd, [view[i * size : (i + 1) * size]], row * size) != size:
                raise MapCorruptError(f"shard file {shards.path(shard).name} is truncated: "
                                      f"committed vertex {vid} is lost")
        return out

    def close(self) -> None:
        for fd in self._fds.values():
            os.close(fd)
        self._fds.clear()

    def __del__(self) -> None:
        self.close()


def sample_ids(committed: int, size: int, generation: int) -> Int64Array:
    """A seeded sample of ``min(size, committed)`` distinct vertex ids, sorted."""
    rng = np.random.default_rng([SAMPLE_SEED, generation])
    if size >= committed:
        return np.arange(committed, dtype=np.int64)
    return np.sort(rng.choice(committed, size=size, replace=False)).astype(np.int64)


def serialize(index: faiss.Index | faiss.VectorTransform) -> bytes:
    """The FAISS file bytes of ``index`` (so we write and fsync them ourselves)."""
    if isinstance(index, faiss.VectorTransform):
        writer = faiss.VectorIOWriter()
        faiss.write_VectorTransform(index, writer)  # type: ignore[arg-type]
        return faiss.vector_to_array(writer.data).tobytes()
    return faiss.serialize_index(index).tobytes()


def publish_bytes(path: Path, data: bytes) -> int:
    """Publish ``data`` as ``path`` atomically (see :func:`atomic.publish`); return its size."""

    def write(partial: Path) -> None:
        with open(partial, "wb") as out:
            out.write(data)

    publish(path, write, expected_size=len(data))
    return len(data)


def read_faiss(path: Path, mmap: bool = False) -> Any:
    """Read an index file; FAISS's RuntimeError (torn, garbled) becomes an OSError."""
    try:
        return faiss.read_index(str(path), faiss.IO_FLAG_MMAP if mmap else 0)
    except RuntimeError as exc:
        raise OSError(errno.EIO, f"{path.name}: {exc}") from exc


@dataclass
class Model:
    """PCA (or None) and the trained, empty IVF index of one generation."""

    kind: str
    pca: faiss.VectorTransform | None
    ivf: Any
    #: The map's learned projection, applied first (raw rows in, indexed space out).
    projection: Projection | None = None

    @property
    def nlist(self) -> int:
        return int(self.ivf.nlist)

    def transform(self, rows: Descriptors) -> Descriptors:
        """Raw rows in the indexed space (the projection, then the PCA, if any),
        C-contiguous float32."""
        rows = (np.ascontiguousarray(rows, dtype=np.float32) if self.projection is None
                else self.projection.apply(rows))
        return rows if self.pca is None else self.pca.apply(rows)

    def publish(self, directory: Path, generation: int) -> tuple[int, int]:
        """Write the model files of ``generation``; return ``(model bytes, pca bytes)``."""
        pca_bytes = 0
        if self.pca is not None:
            pca_bytes = publish_bytes(directory / pca_name(generation), serialize(self.pca))
        return publish_bytes(directory / model_name(generation), serialize(self.ivf)), pca_bytes

    @classmethod
    def read(cls, directory: Path, generation: int, kind: str, with_pca: bool) -> Model:
        ivf = read_faiss(directory / model_name(generation))
        pca = None
        if with_pca:
            try:
                pca = faiss.read_VectorTransform(str(directory / pca_name(generation)))
            except RuntimeError as exc:
                raise OSError(errno.EIO, f"{pca_name(generation)}: {exc}") from exc
        return cls(kind, pca, ivf)


def list_count(config: StoreConfig, vertices: int) -> int:
    """IVF lists of a model trained on a map of ``vertices``: ``index_nlist``, or with
    ``index_nlist`` 0 the square root of the vertices it serves until it is trained again
    (``index_retrain_growth`` times ``vertices``; ``vertices`` alone with growth 0), at least
    :data:`MIN_LISTS`. O(1).

    >>> from sprint_map.storage.store_config import MIN_TRAIN, StoreConfig
    >>> list_count(StoreConfig(dim=128), 800_000), list_count(StoreConfig(dim=128), 3_200_000)
    (1789, 3578)
    >>> list_count(StoreConfig(dim=128, index_nlist=1024), 3_200_000)
    1024
    """
    if config.index_nlist:
        return config.index_nlist
    serves = vertices * max(config.index_retrain_growth, 1.0)
    return max(MIN_LISTS, round(math.sqrt(serves)))


def train_sample_size(config: StoreConfig, vertices: int) -> int:
    """Vertices a model for a map of ``vertices`` is trained on: ``index_train_sample``, or
    more where :func:`list_count` asks for more lists than that feeds
    (:data:`POINTS_PER_LIST` each), within :data:`TRAIN_SAMPLE_BYTES` of descriptors. O(1).
    """
    wanted = POINTS_PER_LIST * list_count(config, vertices)
    budget = TRAIN_SAMPLE_BYTES // (4 * config.dim)
    return max(config.index_train_sample, min(wanted, budget))


def train_model(config: StoreConfig, kind: str, sample: Descriptors, vertices: int) -> Model:
    """Train PCA (when ``dim > index_pca_dim``) and the IVF quantizer on ``sample`` rows of a
    map of ``vertices``.

    The number of lists is :func:`list_count`'s but at most ``len(sample) / 39`` (FAISS's
    minimum training points per list), so a small map trains a smaller quantizer.

    Notes
    -----
    O(n_sample * nlist * d * KMEANS_ITER) for the coarse k-means, plus the PQ codebooks
    (O(n_sample * 256 * d * KMEANS_ITER)) and for PCA O(PCA_SAMPLE * dim^2 + dim^3).
    """
    if kind not in APPROX_KINDS:
        raise ValueError(f"no approximate index kind {kind!r}")
    sample = np.ascontiguousarray(sample, dtype=np.float32)
    d = config.index_dim
    pca = None
    if d < config.dim:
        # A random rotation after the PCA spreads the variance evenly over the PQ sub-vectors.
        pca = faiss.PCAMatrix(config.dim, d, 0, kind == "ivf-pq")
        pca.train(sample[:: max(1, len(sample) // PCA_SAMPLE)])
        sample = pca.apply(sample)
    nlist = max(1, min(list_count(config, vertices), len(sample) // POINTS_PER_LIST))
    quantizer = faiss.IndexFlatL2(d)
    ivf: Any
    if kind == "ivf-pq":
        ivf = faiss.IndexIVFPQ(quantizer, d, nlist, config.pq_m, 8)
        ivf.do_polysemous_training = False
        ivf.pq.cp.niter = KMEANS_ITER
        ivf.pq.cp.min_points_per_centroid = 1  # a small map: no warning, fewer points is fine
    else:
        ivf = faiss.IndexIVFScalarQuantizer(quantizer, d, nlist, faiss.ScalarQuantizer.QT_8bit,
                                            faiss.METRIC_L2, True)
    ivf.own_fields = True
    quantizer.this.disown()  # type: ignore[attr-defined]
    ivf.cp.niter = KMEANS_ITER
    ivf.cp.min_points_per_centroid = 1
    use_threads(len(sample))
    ivf.train(sample)
    return Model(kind, pca, ivf)
