"""A descriptor projection learned from the map's own merged edges, and its files.

Every merged edge joins two views of one place under two conditions. :func:`learn_projection`
turns those pairs into a linear map that makes the descriptor condition-invariant:

1. centre on the mean of the map's rows and keep their ``LEARN_PCA_DIM`` (256) principal
   directions (the pairs are too few to estimate a full within-place covariance);
2. whiten the within-place differences ``a - b`` of the pairs there (their covariance plus
   ``LEARN_SHRINK`` times its median variance on the diagonal, so that few pairs or a few
   wrong ones cannot make a quiet direction arbitrarily loud);
3. keep the ``dim_out`` directions of the whitened space in which the map's rows vary most;
4. L2-normalise the result (:meth:`Projection.apply`).

It is *regularised by its own evidence*: with fewer than ``learn_min_pairs`` pairs nothing is
learned, and a projection is adopted only if, trained without a held-back fifth of the pairs
(blocks of consecutive edges), it retrieves that fifth's partners better than the plain
descriptor does (recall@1 within ``HELDOUT_TOLERANCE`` vertices, both ways), by more than
chance explains (:func:`required_gain`). The adopted projection is then trained on every
pair.

Files: ``projection.f32`` (the mean, then the ``dim_in x dim_out`` matrix, raw little-endian
float32) lives in the projection's own index directory ``index/pGGGGGG/``;
``index/learned.json`` (the pointer, published atomically: the commit point) names it with its
size and BLAKE2b-128 checksum (see :mod:`~sprint_map.storage.index.map_index`).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from sprint_map.util.arrays import Descriptors, Int64Array

if TYPE_CHECKING:
    import faiss
else:  # imported on first use: commands that only read LMDB never load it
    from sprint_map.util.lazy import faiss

__all__ = ["HELDOUT_TOLERANCE", "LEARNED", "LEARN_PCA_DIM", "LEARN_SHRINK", "PROJECTION_FILE",
           "LearnReport", "Learned", "Projection", "heldout_recall", "learn_projection",
           "read_learned"]

#: The pointer file in ``index/``.
LEARNED = "learned.json"
#: The projection's matrix file in its ``index/pGGGGGG/`` directory.
PROJECTION_FILE = "projection.f32"
#: Principal directions of the map's rows the within-place whitening works in.
LEARN_PCA_DIM = 256
#: Shrinkage of the within-place covariance: this times its median variance is added to its
#: diagonal (measured on Nordland: 1.0 gives +14 / +8 points k-NN@1; 3.0 the same).
LEARN_SHRINK = 1.0
#: Pairs per held-back block and one block in ``HELDOUT_EVERY`` is held back.
HELDOUT_BLOCK = 25
HELDOUT_EVERY = 5
#: Held-back pairs scored at most (the score is O(held^2): 2,000 pairs, 32 MB of distances).
HELDOUT_MAX = 2000
#: A held-back pair is retrieved when the partner found is within this many vertex ids.
HELDOUT_TOLERANCE = 2
#: The least gain in held-back recall@1 that adopts a projection (see ``required_gain``).
MIN_GAIN = 0.01
#: Rows of the map the mean and the principal directions are estimated on at most.
ROW_SAMPLE = 20000


def checksum_bytes(data: bytes) -> str:
    """BLAKE2b-128 of ``data``, hex (the index manifest's checksum). O(len(data))."""
    import hashlib  # (here: `info` needs no OpenSSL)

    return hashlib.blake2b(data, digest_size=16).hexdigest()


@dataclass
class Projection:
    """``y = normalise((x - mean) @ matrix)``: ``mean`` (dim_in,), ``matrix`` (dim_in, dim_out)."""

    mean: np.ndarray
    matrix: np.ndarray
    _cast: dict[type, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict, repr=False,
                                                             compare=False)
    _fast: Any = field(default=None, repr=False, compare=False)

    @property
    def dim_in(self) -> int:
        return int(self.matrix.shape[0])

    @property
    def dim_out(self) -> int:
        return int(self.matrix.shape[1])

    def apply(self, rows: Descriptors, *, exact: bool = True) -> Descriptors:
        """Projected, L2-normalised rows (float32, C-contiguous). Computed in float64 and
        rounded, so a row's result does not depend on the batch it comes in (``check``
        compares the index with rows projected again); ``exact=False`` computes in float32
        through FAISS (its threads follow ``use_threads``: numpy's BLAS threads cost
        milliseconds per small product on a loaded machine), for searches, whose results are
        only compared with each other. O(len(rows) * dim_in * dim_out)."""
        if not exact:
            if self._fast is None:
                fast = faiss.LinearTransform(self.dim_in, self.dim_out, True)
                faiss.copy_array_to_vector(np.ascontiguousarray(self.matrix.T, dtype=np.float32)
                                           .ravel(), fast.A)
                faiss.copy_array_to_vector(-(self.mean.astype(np.float64) @ self.matrix.astype(
                    np.float64)).astype(np.float32), fast.b)
                fast.is_trained = True
                self._fast = fast
            out = self._fast.apply(np.ascontiguousarray(rows, dtype=np.float32))
            out /= np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)
            return np.ascontiguousarray(out, dtype=np.float32)
        kind = np.float64
        cast = self._cast.get(kind)
        if cast is None:  # converted once: a query's projection is then one small product
            cast = self._cast[kind] = (self.mean.astype(kind), self.matrix.astype(kind))
        x = np.asarray(rows, dtype=kind) - cast[0]
        y = x @ cast[1]
        y /= np.maximum(np.linalg.norm(y, axis=1, keepdims=True), 1e-12)
        return np.ascontiguousarray(y, dtype=np.float32)

    def to_bytes(self) -> bytes:
        return (np.ascontiguousarray(self.mean, dtype="<f4").tobytes()
                + np.ascontiguousarray(self.matrix, dtype="<f4").tobytes())

    @classmethod
    def from_bytes(cls, data: bytes, dim_in: int, dim_out: int) -> Projection:
        """ValueError if ``data`` is not ``4 * dim_in * (1 + dim_out)`` bytes of finite floats."""
        if len(data) != 4 * dim_in * (1 + dim_out):
            raise ValueError(f"{len(data)} bytes, a {dim_in}x{dim_out} projection takes "
                             f"{4 * dim_in * (1 + dim_out)}")
        flat = np.frombuffer(data, dtype="<f4").astype(np.float32)
        if not np.isfinite(flat).all():
            raise ValueError("not finite")
        return cls(flat[:dim_in].copy(), flat[dim_in:].reshape(dim_in, dim_out).copy())


@dataclass(frozen=True)
class Learned:
    """What ``index/learned.json`` records: the projection in use (generation 0: none) and
    when the map last tried to learn (its edge count then)."""

    attempted_at_edges: int = 0
    generation: int = 0
    pairs: int = 0
    dim_in: int = 0
    dim_out: int = 0
    trained_at_edges: int = 0
    file_bytes: int = 0
    checksum: str = ""
    heldout_recall_before: float = 0.0
    heldout_recall_after: float = 0.0

    @property
    def directory_name(self) -> str:
        return f"p{self.generation:06d}"

    def encode(self) -> bytes:
        return json.dumps({"format": 1, **asdict(self)}, indent=1).encode()

    @classmethod
    def decode(cls, raw: bytes) -> Learned:
        """ValueError if ``raw`` is not a pointer of this format with fields of their types."""
        try:
            data: dict[str, Any] = json.loads(raw)
            if data.pop("format") != 1:
                raise ValueError("unknown format")
            learned = cls(**data)
        except (TypeError, KeyError, AttributeError, RecursionError, UnicodeDecodeError,
                json.JSONDecodeError) as exc:
            raise ValueError(f"not a projection pointer: {exc}") from exc
        ints = [learned.attempted_at_edges, learned.generation, learned.pairs, learned.dim_in,
                learned.dim_out, learned.trained_at_edges, learned.file_bytes]
        if not all(type(v) is int and 0 <= v < 1 << 63 for v in ints) or not isinstance(
                learned.checksum, str) or not all(
                isinstance(v, int | float) for v in (learned.heldout_recall_before,
                                                     learned.heldout_recall_after)):
            raise ValueError("not a projection pointer: a field has the wrong type")
        if learned.generation and (learned.dim_in < 1 or learned.dim_out < 1 or
                                   learned.file_bytes != 4 * learned.dim_in * (1 + learned.dim_out)):
            raise ValueError("not a projection pointer: its sizes disagree")
        return learned

    def read_projection(self, index_dir: Path) -> Projection:
        """The projection file this pointer names, verified (size, checksum, values).

        Raises ValueError (bad bytes) or OSError (missing, unreadable). O(file size)."""
        data = (index_dir / self.directory_name / PROJECTION_FILE).read_bytes()
        if len(data) != self.file_bytes:
            raise ValueError(f"{self.directory_name}/{PROJECTION_FILE} is torn: {len(data)} "
                             f"bytes, recorded {self.file_bytes}")
        if checksum_bytes(data) != self.checksum:
            raise ValueError(f"{self.directory_name}/{PROJECTION_FILE} fails its checksum "
                             "(corrupt bytes)")
        return Projection.from_bytes(data, self.dim_in, self.dim_out)

    def describe(self) -> dict[str, int] | None:
        """``info``'s ``projection``: None, or ``{pairs, dim_out, trained_at_edges}``."""
        if not self.generation:
            return None
        return {"pairs": self.pairs, "dim_out": self.dim_out,
                "trained_at_edges": self.trained_at_edges}


def read_learned(index_dir: Path) -> Learned:
    """The pointer in ``index_dir`` (``Learned()``: none); ValueError if it is garbled."""
    try:
        raw = (index_dir / LEARNED).read_bytes()
    except FileNotFoundError:
        return Learned()
    return Learned.decode(raw)


@dataclass(frozen=True)
class LearnReport:
    """What ``index --learn`` prints (``projection`` is the adopted one, else None)."""

    pairs: int
    dim_in: int
    dim_out: int
    adopted: bool
    heldout_recall_before: float
    heldout_recall_after: float
    reason: str = ""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def heldout_recall(a: Descriptors, b: Descriptors, a_ids: Int64Array, b_ids: Int64Array,
                   tolerance: int = HELDOUT_TOLERANCE) -> float:
    """Recall@1 of pairs ``(a[i], b[i])`` (vertex ids ``a_ids``, ``b_ids``): each ``a[i]``
    searched among all ``b`` finds a row whose vertex is within ``tolerance`` of ``b_ids[i]``,
    and each ``b[i]`` among all ``a`` likewise; the mean of both ways. O(n^2 * d)."""
    def one_way(q: np.ndarray, db: np.ndarray, want: np.ndarray) -> float:
        q64, db64 = q.astype(np.float64), db.astype(np.float64)
        dist = (q64 ** 2).sum(1)[:, None] - 2 * q64 @ db64.T + (db64 ** 2).sum(1)[None, :]
        return float(np.mean(np.abs(want[dist.argmin(1)] - want) <= tolerance))

    return 0.5 * (one_way(a, b, b_ids) + one_way(b, a, a_ids))


def required_gain(before: float, held: int) -> float:
    """The gain in held-back recall a projection must show to be adopted: two standard
    errors of the plain descriptor's recall over ``held`` pairs searched both ways, and at
    least ``MIN_GAIN``: a gain that could be chance (wrong or too few pairs) is refused."""
    return max(MIN_GAIN, 2.0 * float(np.sqrt(before * (1 - before) / max(2 * held, 1))))


def _principal(rows: Descriptors) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(mean, basis (dim_in, p), rows centred in the basis)``: the map rows' ``p`` =
    ``LEARN_PCA_DIM`` principal directions, from their covariance. O(n * dim^2 + dim^3)."""
    x = rows.astype(np.float64)
    mean = x.mean(axis=0)
    x -= mean
    p = min(LEARN_PCA_DIM, x.shape[1], x.shape[0])
    _, vectors = np.linalg.eigh(x.T @ x)
    basis = np.ascontiguousarray(vectors[:, ::-1][:, :p])
    return mean, basis, x @ basis


def _fit(mean: np.ndarray, basis: np.ndarray, z: np.ndarray, a: Descriptors, b: Descriptors,
         dim_out: int) -> Projection:
    """The projection of the module docstring from the map's principal ``basis`` (rows ``z``
    in it) and pairs ``(a, b)``. O(n_pairs * dim_in * p + n_rows * p^2 + p^3)."""
    p = basis.shape[1]
    diff = (a.astype(np.float64) - b.astype(np.float64)) @ basis
    within = diff.T @ diff / max(len(diff), 1)
    within += (LEARN_SHRINK * float(np.median(np.diag(within))) + 1e-12) * np.eye(p)
    values, vectors = np.linalg.eigh(within)
    whiten = vectors / np.sqrt(values)
    w = z @ whiten
    _, spread = np.linalg.eigh(w.T @ w)
    matrix = basis @ whiten @ spread[:, ::-1][:, : min(dim_out, p)]
    matrix /= np.linalg.norm(matrix, axis=0).mean()  # scale-free: the output is normalised
    return Projection(mean.astype(np.float32), matrix.astype(np.float32))


def learn_projection(rows: Descriptors, a: Descriptors, b: Descriptors, a_ids: Int64Array,
                     b_ids: Int64Array, *, dim_out: int, min_pairs: int
                     ) -> tuple[LearnReport, Projection | None]:
    """Learn a projection from pairs ``(a[i], b[i])`` of vertices ``(a_ids[i], b_ids[i])``
    (the map's merged edges, in vertex order) and a sample ``rows`` of the map.

    Returns the report and the projection to adopt (None: keep the plain descriptor, the
    report says why): too few pairs, or no gain on the held-back pairs.

    Notes
    -----
    O(n_rows * dim_in^2 + n_pairs * (dim_in * p + p^2) + held-back^2 * d) with p = 256.
    """
    n, dim_in = len(a), int(a.shape[1]) if a.ndim == 2 else int(rows.shape[1])
    dim_out = min(dim_out, dim_in)
    if n < min_pairs or n < 2 * HELDOUT_BLOCK * HELDOUT_EVERY:
        return LearnReport(n, dim_in, dim_out, False, 0.0, 0.0,
                           f"{n} merged pairs, fewer than the {max(min_pairs, 250)} needed"), None
    block = np.arange(n) // HELDOUT_BLOCK
    held = block % HELDOUT_EVERY == HELDOUT_EVERY // 2
    scored = held  # held-back blocks scored: at most HELDOUT_MAX pairs, spread evenly
    blocks = np.unique(block[held])
    if len(blocks) * HELDOUT_BLOCK > HELDOUT_MAX:
        pick = blocks[np.linspace(0, len(blocks) - 1, HELDOUT_MAX // HELDOUT_BLOCK).astype(int)]
        scored = np.isin(block, pick)
    mean, basis, z = _principal(rows)
    dim_out = min(dim_out, basis.shape[1])
    trial = _fit(mean, basis, z, a[~held], b[~held], dim_out)
    before = heldout_recall(a[scored], b[scored], a_ids[scored], b_ids[scored])
    after = heldout_recall(trial.apply(a[scored]), trial.apply(b[scored]), a_ids[scored],
                           b_ids[scored])
    if after - before < required_gain(before, int(scored.sum())):
        return LearnReport(n, dim_in, dim_out, False, before, after,
                           "no significant gain on the held-back pairs"), None
    return (LearnReport(n, dim_in, dim_out, True, before, after),
            _fit(mean, basis, z, a, b, dim_out))
