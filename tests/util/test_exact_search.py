"""Exact search whose answer for a query does not depend on its batch (exact_search.py).

The map's flat search must give a query the same ids and distances, bit for bit, searched
alone, in a small batch or in a large one (the service batches sessions' frames, offline
``localize`` searches 256 at a time): these tests compare every batch split with the brute
force of :func:`pair_distances` ordered by (distance, id), exact ties included.
"""

from __future__ import annotations

import faiss
import numpy as np
import pytest

from sprint_map.config import MapConfig
from sprint_map.map import SprintMap
from sprint_map.util.exact_search import (
    MARGIN,
    RETRY_FACTOR,
    candidate_distances,
    certified_search,
    distance_error_bound,
    margin_for,
    pair_distances,
    pair_error_bound,
    row_norm_max,
)


def float64_distances(query: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """The real squared distances, to float64 precision."""
    return ((rows.astype(np.float64) - query.astype(np.float64)) ** 2).sum(axis=1)


def brute(vectors: np.ndarray, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The specification: top k by pair_distances over every row, ties by id."""
    d_out, i_out = [], []
    ids = np.arange(len(vectors))
    for q in queries:
        dist = pair_distances(q, vectors)
        order = np.lexsort((ids, dist))[:k]
        d_out.append(dist[order])
        i_out.append(ids[order])
    return np.array(d_out), np.array(i_out)


@pytest.fixture
def world(rng):
    """400 rows of dim 48 with exact duplicates (ties) and queries near and on them."""
    vectors = rng.standard_normal((400, 48)).astype(np.float32)
    vectors[200:260] = vectors[100:160]  # 60 exact duplicates: tied distances
    queries = np.concatenate([vectors[rng.choice(400, 40)] + 0.05 * rng.standard_normal(
        (40, 48)).astype(np.float32), vectors[100:110]]).astype(np.float32)
    return vectors, queries


def flat_fast(vectors: np.ndarray):
    index = faiss.IndexFlatL2(vectors.shape[1])
    index.add(vectors)
    return index.search


@pytest.mark.parametrize("k", [1, 10, 30])
@pytest.mark.parametrize("split", [1, 3, 7, 50])
def test_any_batch_split_gives_the_brute_force_answer(world, k, split):
    vectors, queries = world
    fast, norm = flat_fast(vectors), row_norm_max(vectors)
    want = brute(vectors, queries, k)
    parts = [certified_search(fast, vectors, norm, queries[i : i + split], k)
             for i in range(0, len(queries), split)]
    got = (np.concatenate([d for d, _ in parts]), np.concatenate([i for _, i in parts]))
    np.testing.assert_array_equal(got[1], want[1])
    np.testing.assert_array_equal(got[0], want[0])


def test_a_perturbed_fast_search_is_caught_by_the_certificate(world):
    """A fast search whose distances err (within the bound) and whose list misses the true
    neighbours still gives the exact answer: the uncertified queries are recomputed."""
    vectors, queries = world
    norm = row_norm_max(vectors)
    exact_fast = flat_fast(vectors)

    def wrong(q, n):  # right distances for the wrong (the farthest) candidates
        d, i = exact_fast(q, len(vectors))
        return d[:, ::-1][:, :n].copy(), i[:, ::-1][:, :n].copy()

    got = certified_search(wrong, vectors, norm, queries, 5)
    want = brute(vectors, queries, 5)
    # No query's fast candidates hold its true top 5, so each answer equal to the brute force
    # is one recomputed against every vertex (the fallback taken for every query).
    offered = wrong(queries, 5 + MARGIN)[1]
    assert not any(set(want[1][q]) <= set(offered[q]) for q in range(len(queries)))
    np.testing.assert_array_equal(got[1], want[1])


def test_a_fast_search_that_finds_too_few_keeps_what_it_found(world):
    """Candidate lists cut short (-1 padded: FAISS leaves out rows at an infinite distance)
    give the rows found, re-measured and ordered by (distance, id), then -1; full lists the
    exact answer."""
    vectors, queries = world
    exact_fast = flat_fast(vectors)

    def short(q, n):
        d, i = exact_fast(q, n)
        d[::2, 3:], i[::2, 3:] = np.finfo(np.float32).max, -1
        return d, i

    got_d, got_i = certified_search(short, vectors, row_norm_max(vectors), queries, 5)
    want_d, want_i = brute(vectors, queries, 5)
    np.testing.assert_array_equal(got_i[1::2], want_i[1::2])
    np.testing.assert_array_equal(got_d[1::2], want_d[1::2])
    found = short(queries, 5 + MARGIN)[1][::2, :3]
    for q, ids in enumerate(found):
        exact = pair_distances(queries[2 * q], vectors[ids])
        order = np.lexsort((ids, exact))
        assert got_i[2 * q].tolist() == ids[order].tolist() + [-1, -1]
        np.testing.assert_array_equal(got_d[2 * q, :3], exact[order])


def test_a_query_of_huge_values_finds_nothing_and_warns_not(world):
    """Squared distances past float32 (a fuzzer's frame): no hit, as FAISS gives, no error."""
    vectors, _ = world
    huge = np.full((2, vectors.shape[1]), 3e38, np.float32)
    with np.errstate(all="raise"):
        d, i = certified_search(flat_fast(vectors), vectors, row_norm_max(vectors), huge, 5)
    assert (i == -1).all()


@pytest.mark.parametrize("candidates", [18, 80])
@pytest.mark.parametrize("dim", [3, 16, 128, 129, 1764])
def test_candidate_distances_are_pair_distances_bit_for_bit(rng, dim, candidates):
    """All queries at once (the certification's fast path) as one query at a time, in small
    and large dimensions, with few and many candidates."""
    vectors = (3 * rng.standard_normal((500, dim))).astype(np.float32)
    queries = (3 * rng.standard_normal((70, dim))).astype(np.float32)
    cand = rng.integers(0, 500, (70, candidates))
    got = candidate_distances(queries, vectors, cand)
    for q in range(len(queries)):
        np.testing.assert_array_equal(got[q], pair_distances(queries[q], vectors[cand[q]]))


@pytest.fixture
def blas_always():
    """FAISS's matrix-product distances for any batch size, for the test's duration."""
    before = faiss.cvar.distance_compute_blas_threshold
    faiss.cvar.distance_compute_blas_threshold = 1
    yield
    faiss.cvar.distance_compute_blas_threshold = before


@pytest.mark.usefixtures("blas_always")
def test_matrix_product_distances_are_within_the_bound(rng):
    for dim in (16, 256, 1764):
        vectors = (3 * rng.standard_normal((300, dim))).astype(np.float32)
        queries = (3 * rng.standard_normal((16, dim))).astype(np.float32)
        d, i = flat_fast(vectors)(queries, 300)
        norm = row_norm_max(vectors)
        for q in range(len(queries)):
            exact = float64_distances(queries[q], vectors[i[q]])
            bound = distance_error_bound(dim, float(np.linalg.norm(queries[q])), norm)
            assert np.abs(d[q] - exact).max() <= bound


@pytest.mark.parametrize("dim", [1, 3, 8, 48, 129, 1764])
def test_pair_distances_are_within_their_bound_and_ignore_alignment(rng, dim):
    """Within pair_error_bound of the real distance; the same bits wherever the query and
    the rows sit in memory (shifted by 1-7 floats: another alignment) and whichever rows
    are measured with them."""
    rows = (3 * rng.standard_normal((200, dim))).astype(np.float32)
    query = (3 * rng.standard_normal(dim)).astype(np.float32)
    got = pair_distances(query, rows)
    exact = float64_distances(query, rows)
    assert (np.abs(got - exact) <= pair_error_bound(dim) * exact).all()
    for shift in range(1, 8):
        q_buf = np.empty(dim + 8, np.float32)
        r_buf = np.empty(rows.size + 8, np.float32)
        q_buf[shift : shift + dim] = query
        r_buf[shift : shift + rows.size] = rows.ravel()
        shifted = pair_distances(q_buf[shift : shift + dim],
                                 r_buf[shift : shift + rows.size].reshape(rows.shape))
        np.testing.assert_array_equal(shifted, got)
    np.testing.assert_array_equal(pair_distances(query, rows[::-7]), got[::-7])


def test_candidate_distances_refuse_rows_that_are_not_there(rng):
    vectors = rng.standard_normal((10, 4)).astype(np.float32)
    with pytest.raises(IndexError):
        candidate_distances(vectors[:1], vectors, np.array([[3, 10]]))
    with pytest.raises(IndexError):
        candidate_distances(vectors[:1], vectors, np.array([[-1]]))
    with pytest.raises(ValueError):
        candidate_distances(vectors[:2, :3], vectors, np.array([[1], [2]]))


def test_map_search_and_localize_agree_frame_by_frame(tmp_path, rng):
    """Through the map: searching frames one by one, in batches, and offline localize vs
    Localizer.step give identical ids, distances and decisions."""
    places = rng.standard_normal((300, 24)).astype(np.float32)
    query = (places[50:170] + 0.3 * rng.standard_normal((120, 24))).astype(np.float32)
    with SprintMap.create(tmp_path / "m", MapConfig(dim=24)) as m:
        m.ingest(places, name="a")
        m.ingest(places + 0.2 * rng.standard_normal(places.shape).astype(np.float32), name="b")
        alone = [m.search(row[None], 10) for row in query]
        batch = m.search(query, 10)
        np.testing.assert_array_equal(np.concatenate([i for _, i in alone]), batch[1])
        np.testing.assert_array_equal(np.concatenate([d for d, _ in alone]), batch[0])
        offline, _ = m.localize(query)
        streamed = m.localizer()
        assert [streamed.step(row) for row in query] == offline


def test_an_uncertified_query_is_searched_deeper_before_every_row(world):
    """A fast search whose short lists miss the true neighbours (but whose deeper lists hold
    them) gives the exact answer from the second, deeper search."""
    vectors, queries = world
    exact_fast = flat_fast(vectors)
    asked: list[int] = []

    def shallow_wrong(q, n):
        asked.append(n)
        d, i = exact_fast(q, len(vectors))
        if n > 5 + margin_for(5):  # the retry: the true lists
            return d[:, :n].copy(), i[:, :n].copy()
        return d[:, -n:][:, ::-1].copy(), i[:, -n:][:, ::-1].copy()  # the farthest rows

    got = certified_search(shallow_wrong, vectors, row_norm_max(vectors), queries, 5)
    want = brute(vectors, queries, 5)
    np.testing.assert_array_equal(got[1], want[1])
    np.testing.assert_array_equal(got[0], want[0])
    assert asked == [5 + margin_for(5), RETRY_FACTOR * (5 + margin_for(5))]

