"""faiss flat search against brute force in float64.

Tolerances: faiss squared-L2 distances (float32, computed as |x|^2 + |y|^2 - 2 x.y)
vs float64 differences, rtol 1e-5 with atol 1e-4 (values up to ~100). Indices are
compared exactly on data whose consecutive sorted distances differ by more than 2e-3
(the float32 error is below 1e-4 there).
"""

from __future__ import annotations

import numpy as np
import pytest

from vprflow.search.flat import flat_knn


def brute_force(database, queries):
    """All squared L2 distances by explicit loops, float64."""
    database = np.asarray(database, np.float64)
    queries = np.asarray(queries, np.float64)
    out = np.zeros((len(queries), len(database)))
    for q, query in enumerate(queries):
        for r, row in enumerate(database):
            diff = query - row
            out[q, r] = float(diff @ diff)
    return out


def separated(seed, n_db=60, n_q=15, d=8):
    rng = np.random.default_rng(seed)
    database = rng.uniform(-3, 3, (n_db, d)).astype(np.float32)
    queries = rng.uniform(-3, 3, (n_q, d)).astype(np.float32)
    return database, queries


@pytest.mark.parametrize("seed", [0, 1, 3])
@pytest.mark.parametrize("k", [1, 5, 20])
def test_search_matches_brute_force(seed, k):
    database, queries = separated(seed)
    full = brute_force(database, queries)
    order = np.argsort(full, axis=1, kind="stable")[:, :k]
    expected = np.take_along_axis(full, order, axis=1)
    # Well separated: no near-ties among the first k + 1 neighbours.
    gaps = np.diff(np.sort(full, axis=1)[:, : k + 1], axis=1)
    assert gaps.min() > 2e-3
    distances, indices = flat_knn(database, queries, k)
    assert distances.shape == indices.shape == (len(queries), k)
    np.testing.assert_array_equal(indices, order)
    np.testing.assert_allclose(distances, expected, rtol=1e-5, atol=1e-4)


def test_search_caps_k_at_database_size_and_finds_exact_copies():
    database, _ = separated(3, n_db=6)
    distances, indices = flat_knn(database, database[::-1], 50)
    assert indices.shape == (6, 6)
    np.testing.assert_array_equal(indices[:, 0], np.arange(6)[::-1])
    np.testing.assert_allclose(distances[:, 0], 0.0, atol=1e-4)
    assert (indices >= 0).all()


@pytest.mark.parametrize("seed", [0, 1])
def test_ranked_distances_are_each_pairs_float64_distance_rounded_once(seed):
    """Any ranking (a shuffled one, and faiss's own; long vectors of large values, as
    SNSM's): each entry is the float64 distance of its pair, rounded to float32."""
    from vprflow.search.flat import ranked_distances

    rng = np.random.default_rng(seed)
    database = (rng.standard_normal((30, 3136)) * 10).astype(np.float32)
    queries = (rng.standard_normal((7, 3136)) * 10).astype(np.float32)
    ranking = np.stack([rng.permutation(30)[:12] for _ in range(7)])
    exact = brute_force(database, queries)
    expected = np.take_along_axis(exact, ranking, axis=1).astype(np.float32)
    np.testing.assert_array_equal(ranked_distances(database, queries, ranking), expected)
    _, found = flat_knn(database, queries, 12)
    np.testing.assert_array_equal(
        ranked_distances(database, queries, found),
        np.take_along_axis(exact, found, 1).astype(np.float32),
    )
