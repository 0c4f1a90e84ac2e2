"""Exact k-NN whose answer for a query never depends on the other queries of its batch.

FAISS's flat search computes distances one way for a few queries (one pair at a time) and
another way for a batch (``|x|^2 + |y|^2 - 2 x.y`` through a matrix product): the two differ in
the last float bits, so the same frame could get a different answer searched alone (a vehicle
streaming), in a batch of 16 (the service batching sessions) or of 256 (offline ``localize``).
:func:`certified_search` makes every batch size give the same answer, bit for bit:

1. the batch is searched the fast way (FAISS, matrix product) for ``k + margin`` candidates;
2. each candidate's distance is recomputed by :func:`pair_distances`, a function of the two
   vectors alone (float64 squares summed in a fixed order, rounded to float32), and the
   candidates ordered by ``(distance, vertex id)`` (so even exact ties are ordered the same);
3. the answer is *certified*: the matrix product's error is bounded
   (:func:`distance_error_bound`), so if the k-th recomputed distance plus that bound is below
   the candidate list's worst fast distance, no vertex outside the list can enter the top k.
   A query that is not certified (rare: 0 of 3,576 Nordland queries with ``margin`` 8) is
   recomputed against every vertex with :func:`pair_distances`.

So the answer is the top ``k`` by :func:`pair_distances` over the whole index, ties broken by
vertex id: a function of the query and the map only.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import faiss
else:  # imported on first use: commands that only read LMDB never load it
    from sprint_map.util.lazy_faiss import faiss

__all__ = ["BLAS_FROM_QUERIES", "MARGIN", "ExactFlat", "candidate_distances", "certified_search",
           "distance_error_bound", "pair_distances", "row_norm_max"]

#: Extra candidates asked of the fast search, beyond ``k``.
MARGIN = 8
#: Queries from which FAISS's flat search computes distances by matrix product (its default,
#: 20, searches smaller batches pair by pair, reading the whole index once per query). Any
#: threshold gives the same answers (they are certified); :class:`ExactFlat` sets it.
BLAS_FROM_QUERIES = 4
#: float32 unit round-off.
_U = 2.0 ** -24
#: Rows per chunk when a query is recomputed against every vertex.
_CHUNK = 4096
#: float64 values per chunk of :func:`candidate_distances` (16 MB).
_CHUNK_VALUES = 1 << 21


def pair_distances(query: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Squared L2 distances from ``query`` (dim,) to each of ``rows`` (n, dim), float32.

    Each value depends on its two vectors only (not on ``n``, nor on the row's position):
    the differences and squares are taken in float64 and each row summed in the same order.

    Notes
    -----
    O(n * dim), with an (n, dim) float64 temporary.
    """
    diff = rows.astype(np.float64) - query.astype(np.float64)
    np.square(diff, out=diff)
    out: np.ndarray = diff.sum(axis=1).astype(np.float32)
    return out


def row_norm_max(rows: np.ndarray) -> float:
    """The largest L2 norm among ``rows`` (0 for none). O(n * dim)."""
    if not len(rows):
        return 0.0
    return float(np.sqrt(np.einsum("ij,ij->i", rows, rows, dtype=np.float64).max()))


def distance_error_bound(dim: int, query_norm: float, row_norm: float) -> float:
    """A bound on ``|fast - exact|`` for a squared L2 distance computed in float32 by
    ``|x|^2 + |y|^2 - 2 x.y`` with any summation order.

    Each of the three terms errs by at most ``gamma_dim`` times its magnitude
    (``gamma_n = n u / (1 - n u)``), and the sum by a few more round-offs: in all at most
    ``(dim + 3) u (1 + 1%) (|x| + |y|)^2``.
    """
    return (dim + 3) * _U * 1.01 * (query_norm + row_norm) ** 2


def certified_search(
    fast: Callable[[np.ndarray, int], tuple[np.ndarray, np.ndarray]],
    vectors: np.ndarray,
    norm_max: float,
    queries: np.ndarray,
    k: int,
    margin: int = MARGIN,
) -> tuple[np.ndarray, np.ndarray]:
    """The exact top ``k`` of each query, as described in the module docstring.

    Parameters
    ----------
    fast : callable
        ``fast(queries, n)`` -> ``(distances, ids)``: a flat search over ``vectors`` (ids are
        row numbers, -1 padded), exact up to :func:`distance_error_bound`.
    vectors : ndarray (n_total, dim)
        The indexed rows.
    norm_max : float
        The largest norm among ``vectors`` (:func:`row_norm_max`).

    Returns
    -------
    (distances, ids) : (nq, k) float32 and int64 arrays
        -1 padded past the index's size (with the fast search's padding distance).

    Notes
    -----
    The fast search, plus O(nq * (k + margin) * dim) to recompute the candidates (vectorised
    over the queries: ~1-2 us a query at dim 128, against ~15 us one query at a time), plus
    O(n_total * dim) for each query not certified.
    """
    total = len(vectors)
    want = min(k + margin, total)
    dist, ids = fast(queries, max(want, k))
    out_d = dist[:, :k].copy()
    out_i = ids[:, :k].copy()
    if not total or not len(queries):
        return out_d, out_i
    dim = vectors.shape[1]
    cand = ids[:, :want]
    # FAISS leaves out rows at an infinite distance (a query of huge values): -1 in the list
    short = (cand < 0).any(axis=1)
    n = min(k, want)
    full = np.flatnonzero(~short)
    if len(full):
        q_full = queries if len(full) == len(queries) else queries[full]
        c_full = cand[full]
        exact = candidate_distances(q_full, vectors, c_full)
        top = np.lexsort((c_full, exact), axis=-1)[:, :n]  # by (distance, id), per query
        out_d[full, :n] = np.take_along_axis(exact, top, axis=1)
        out_i[full, :n] = np.take_along_axis(c_full, top, axis=1)
        if want < total:
            qnorms = np.sqrt(np.einsum("ij,ij->i", q_full, q_full, dtype=np.float64))
            bound = (dim + 3) * _U * 1.01 * (qnorms + norm_max) ** 2  # distance_error_bound
            kth = out_d[full, n - 1].astype(np.float64)
            worst_fast = dist[full, want - 1].astype(np.float64)
            for q in full[~(kth + bound < worst_fast - _U * np.abs(worst_fast))]:
                every, exact_q, order_q = _everything(queries[q], vectors)
                out_d[q, :n] = exact_q[order_q[:n]]
                out_i[q, :n] = every[order_q[:n]]
    for q in np.flatnonzero(short):  # the rows found, re-measured and ordered; then -1
        found = cand[q][cand[q] >= 0]
        exact_q = pair_distances(queries[q], vectors[found])
        order_q = np.lexsort((found, exact_q))[:k]
        out_d[q, :len(order_q)] = exact_q[order_q]
        out_i[q, :len(order_q)] = found[order_q]
    return out_d, out_i


def candidate_distances(queries: np.ndarray, vectors: np.ndarray, cand: np.ndarray
                        ) -> np.ndarray:
    """``(nq, m)`` float32: :func:`pair_distances` of each query to its ``m`` candidate rows
    ``vectors[cand[q]]``, bit for bit, all queries at once.

    Notes
    -----
    O(nq * m * dim), in chunks of queries whose float64 temporary stays under ~16 MB.
    """
    nq, m = cand.shape
    dim = vectors.shape[1]
    out = np.empty((nq, m), np.float32)
    step = max(1, _CHUNK_VALUES // max(1, m * dim))
    for a in range(0, nq, step):
        b = min(nq, a + step)
        diff = vectors[cand[a:b]].astype(np.float64)
        diff -= queries[a:b, None, :].astype(np.float64)
        np.square(diff, out=diff)
        out[a:b] = diff.sum(axis=2)  # each row summed as pair_distances sums it
    return out


def _everything(query: np.ndarray, vectors: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(ids, distances, order)`` of ``query`` against every row, by (distance, id)."""
    exact = np.concatenate([pair_distances(query, vectors[i : i + _CHUNK])
                            for i in range(0, len(vectors), _CHUNK)])
    ids = np.arange(len(vectors), dtype=np.int64)
    return ids, exact, np.lexsort((ids, exact))


class ExactFlat:
    """:func:`certified_search` over one FAISS flat index (``IndexFlatL2``, or an
    ``IndexIDMap2`` of one whose ids are the row numbers), keeping the rows' largest norm as
    rows are added. Make a new one when the index is replaced.

    Notes
    -----
    A search reads the new rows' norms once (O(new rows * dim)), then see
    :func:`certified_search`.
    """

    def __init__(self, index: Any) -> None:
        self.index = index
        inner = index.index if hasattr(index, "id_map") else index
        self._flat: Any = faiss.downcast_index(inner)
        self._seen = 0
        self._norm = 0.0

    def rows(self) -> np.ndarray:
        """The indexed rows, ``(ntotal, dim)``: a view of FAISS's storage (valid until the
        next add)."""
        total, dim = int(self._flat.ntotal), int(self._flat.d)
        view: np.ndarray = faiss.rev_swig_ptr(self._flat.get_xb(), total * dim).reshape(total,
                                                                                         dim)
        return view

    def search(self, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The exact top ``k`` of each query, independent of the batch (row-number ids)."""
        faiss.cvar.distance_compute_blas_threshold = BLAS_FROM_QUERIES  # a process global
        vectors = self.rows()
        if len(vectors) != self._seen:
            self._norm = max(self._norm, row_norm_max(vectors[self._seen:]))
            self._seen = len(vectors)
        return certified_search(self.index.search, vectors, self._norm,
                                np.ascontiguousarray(queries, dtype=np.float32), k)

