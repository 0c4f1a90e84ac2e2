"""Exact k-NN whose answer for a query never depends on the other queries of its batch.

FAISS's flat search computes distances one way for a few queries (one pair at a time) and
another way for a batch (``|x|^2 + |y|^2 - 2 x.y`` through a matrix product): the two differ in
the last float bits, so the same frame could get a different answer searched alone (a vehicle
streaming), in a batch of 16 (the service batching sessions) or of 256 (offline ``localize``).
:func:`certified_search` makes every batch size give the same answer, bit for bit:

1. the batch is searched the fast way (FAISS, matrix product) for ``k + margin`` candidates;
2. each candidate's distance is recomputed by :func:`pair_distances`, a function of the two
   vectors alone (FAISS's ``fvec_L2sqr``: the differences squared and summed in float32 in
   one fixed order, whatever the batch, the row's position or its alignment), and the
   candidates ordered by ``(distance, vertex id)`` (so even exact ties are ordered the same);
3. the answer is *certified*: the matrix product's error and the recomputation's are bounded
   (:func:`distance_error_bound`, :data:`PAIR_RELATIVE_ERROR`), so if the k-th recomputed
   distance is below what any vertex outside the candidate list could measure, given the
   list's worst fast distance, no such vertex can enter the top k.
   A query that is not certified (rare: of Nordland's 2 x 3,576 queries, 4 with ``k`` 10 and 2
   with ``k`` 64 and its margin of 16) is searched again for :data:`RETRY_FACTOR` times as
   many candidates and certified again (all of those 6); one that still is not is recomputed
   against every vertex with :func:`pair_distances`.

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
    from sprint_map.util.lazy import faiss

__all__ = ["BLAS_FROM_QUERIES", "MARGIN", "RETRY_FACTOR", "ExactFlat", "candidate_distances",
           "certified_search", "distance_error_bound", "margin_for", "pair_distances",
           "pair_error_bound", "row_norm_max"]

#: Extra candidates asked of the fast search beyond ``k``: at least this many, and a quarter of
#: ``k`` for deep searches (:func:`margin_for`).
MARGIN = 8
#: An uncertified query's second fast search asks this many times the first one's candidates.
RETRY_FACTOR = 4
#: Queries from which FAISS's flat search computes distances by matrix product (its default,
#: 20, searches smaller batches pair by pair, reading the whole index once per query). Any
#: threshold gives the same answers (they are certified); :class:`ExactFlat` sets it.
BLAS_FROM_QUERIES = 4
#: float32 unit round-off.
_U = 2.0 ** -24
#: Rows per call of the pass over every row (:func:`certified_search`'s last resort): bounds
#: the id array it needs, whatever the index's size.
_ROWS_PER_PASS = 1 << 16


def pair_distances(query: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Squared L2 distances from ``query`` (dim,) to each of ``rows`` (n, dim), float32.

    Each value depends on its two vectors only (not on ``n``, on the row's position or on
    either vector's alignment in memory): FAISS's ``fvec_L2sqr``, float32 differences squared
    and summed in one fixed vectorised order, within :func:`pair_error_bound` of the exact
    distance.

    Notes
    -----
    O(n * dim), in C, no temporary beyond the ``n`` row numbers.
    """
    rows = np.ascontiguousarray(rows, dtype=np.float32)
    out: np.ndarray = candidate_distances(np.asarray(query)[None, :], rows,
                                          np.arange(len(rows), dtype=np.int64)[None, :])[0]
    return out


def pair_error_bound(dim: int) -> float:
    """A bound on ``|pair - exact| / exact`` for :func:`pair_distances` (``exact`` the real
    squared distance): ``dim`` float32 differences, squares and additions of non-negative
    terms in any order err by at most ``(dim + 3) u (1 + 1%)`` of the sum."""
    return (dim + 3) * _U * 1.01


def margin_for(k: int) -> int:
    """The extra candidates :func:`certified_search` asks for beyond ``k`` by default:
    ``max(MARGIN, k // 4)`` (the gaps between neighbours shrink with depth: with 8 extra,
    3 of 1,500 Nordland queries at ``k`` 64 were not certified, each a pass over the map)."""
    return max(MARGIN, k // 4)


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
    margin: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The exact top ``k`` of each query, as described in the module docstring. Cost: the fast
    search, O(nq * (k + margin) * dim) to recompute the candidates, one deeper fast search for
    the uncertified queries, O(n_total * dim) for each still uncertified.

    Parameters
    ----------
    fast : callable
        ``fast(queries, n)`` -> ``(distances, ids)``: a flat search over ``vectors`` (ids are
        row numbers, -1 padded), exact up to :func:`distance_error_bound`.
    vectors : ndarray (n_total, dim)
        The indexed rows.
    norm_max : float
        The largest norm among ``vectors`` (:func:`row_norm_max`).
    margin : int, optional
        Extra candidates beyond ``k`` (default :func:`margin_for`): a cost, not the answer.

    Returns
    -------
    (distances, ids) : (nq, k) float32 and int64 arrays
        -1 padded past the index's size (with the fast search's padding distance).
    """
    total = len(vectors)
    want = min(k + (margin_for(k) if margin is None else margin), total)
    dist, ids = fast(queries, max(want, k))
    out_d = dist[:, :k].copy()
    out_i = ids[:, :k].copy()
    if not total or not len(queries):
        return out_d, out_i
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
            unsure = full[~_certified(q_full, norm_max, out_d[full, n - 1], dist[full, want - 1])]
            if len(unsure):
                _recheck(fast, vectors, norm_max, queries, unsure, k, min(RETRY_FACTOR * want,
                                                                            total), out_d, out_i)
    for q in np.flatnonzero(short):  # the rows found, re-measured and ordered; then -1
        found = cand[q][cand[q] >= 0]
        exact_q = pair_distances(queries[q], vectors[found])
        order_q = np.lexsort((found, exact_q))[:k]
        out_d[q, :len(order_q)] = exact_q[order_q]
        out_i[q, :len(order_q)] = found[order_q]
    return out_d, out_i


def _certified(queries: np.ndarray, norm_max: float, kth: np.ndarray, worst_fast: np.ndarray
               ) -> np.ndarray:
    """Per query: whether no row outside its candidate list can beat its ``kth`` recomputed
    distance, given the list's ``worst_fast`` distance (:func:`distance_error_bound`)."""
    qnorms = np.sqrt(np.einsum("ij,ij->i", queries, queries, dtype=np.float64))
    dim = queries.shape[1]
    bound = (dim + 3) * _U * 1.01 * (qnorms + norm_max) ** 2  # distance_error_bound
    worst = worst_fast.astype(np.float64)
    # an outside row's exact distance is at least its fast one less the bound, and its
    # recomputed one at least that less the recomputation's relative error
    floor = (worst - _U * np.abs(worst) - bound) * (1.0 - pair_error_bound(dim))
    certified: np.ndarray = kth.astype(np.float64) < floor
    return certified


def _recheck(fast: Callable[[np.ndarray, int], tuple[np.ndarray, np.ndarray]],
             vectors: np.ndarray, norm_max: float, queries: np.ndarray, unsure: np.ndarray,
             k: int, want: int, out_d: np.ndarray, out_i: np.ndarray) -> None:
    """The exact top ``k`` of the queries ``unsure`` (rows of ``queries``), written into
    ``out_d``/``out_i``: from a fast search for ``want`` candidates where that certifies,
    else against every row."""
    q_uns = np.ascontiguousarray(queries[unsure])
    dist, ids = fast(q_uns, want)
    every = np.arange(len(vectors), dtype=np.int64)
    for j, q in enumerate(unsure.tolist()):
        query = q_uns[j]
        cand = ids[j]
        if want < len(vectors) and not (cand < 0).any():
            exact = candidate_distances(query[None, :], vectors, cand[None, :])[0]
            order = np.lexsort((cand, exact))[:k]
            if _certified(query[None, :], norm_max, exact[order[-1:]], dist[j, -1:])[0]:
                out_d[q, :k], out_i[q, :k] = exact[order], cand[order]
                continue
        exact = _all_distances(query, vectors)
        order = np.lexsort((every, exact))[:k]
        out_d[q, :k], out_i[q, :k] = exact[order], every[order]


def _all_distances(query: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """:func:`pair_distances` of ``query`` to every row, :data:`_ROWS_PER_PASS` rows a call
    (O(n * dim))."""
    query = np.asarray(query)[None, :]
    return np.concatenate([
        candidate_distances(query, vectors, np.arange(i, min(i + _ROWS_PER_PASS, len(vectors)),
                                                      dtype=np.int64)[None, :])[0]
        for i in range(0, len(vectors), _ROWS_PER_PASS)] or [np.empty(0, np.float32)])


def candidate_distances(queries: np.ndarray, vectors: np.ndarray, cand: np.ndarray
                        ) -> np.ndarray:
    """``(nq, m)`` float32: :func:`pair_distances` of each query to its ``m`` candidate rows
    ``vectors[cand[q]]``, bit for bit, all queries at once.

    Raises
    ------
    IndexError
        A candidate that is not a row of ``vectors`` (FAISS would read past them).
    ValueError
        Queries not one per candidate list, or not of the rows' dimension.

    Notes
    -----
    O(nq * m * dim) in one call of FAISS's ``fvec_L2sqr_by_idx`` (over the queries on
    FAISS's threads), reading the rows where they are: no gathered copy, no temporary.
    """
    ids = np.ascontiguousarray(cand, dtype=np.int64)
    out = np.empty(ids.shape, np.float32)
    if not out.size:
        return out
    if int(ids.min()) < 0 or int(ids.max()) >= len(vectors):
        raise IndexError(f"candidate rows outside 0..{len(vectors) - 1}")
    queries = np.ascontiguousarray(queries, dtype=np.float32)
    vectors = np.ascontiguousarray(vectors, dtype=np.float32)  # the index's rows: no copy
    if queries.shape != (ids.shape[0], vectors.shape[1]):
        raise ValueError(f"queries of shape {queries.shape} for {ids.shape[0]} candidate lists "
                         f"of rows of dim {vectors.shape[1]}")
    by_idx = faiss.fvec_L2sqr_by_idx  # type: ignore[attr-defined]  # missing from FAISS's stub
    by_idx(faiss.swig_ptr(out), faiss.swig_ptr(queries),
           faiss.swig_ptr(vectors), faiss.swig_ptr(ids), vectors.shape[1], ids.shape[0],
           ids.shape[1])
    return out


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

