"""Top-k lists: merging shards into one search, and agreement between two searches."""

from __future__ import annotations

import numpy as np
import pytest
from knn_helpers import unit_vectors

from vprflow.search.exact import exact_knn
from vprflow.search.topk import merge_knn, topk_agreement


def test_merge_knn_of_shards_equals_one_search():
    rng = np.random.default_rng(29)
    database, queries = unit_vectors(rng, 230, 24), unit_vectors(rng, 12, 24)
    whole = exact_knn(database, queries, 15, device="cpu")
    parts = []
    for start in range(0, len(database), 60):
        d, i = exact_knn(database[start : start + 60], queries, 15, device="cpu")
        parts.append((d, i + start))
    merged = merge_knn(parts, 15)
    np.testing.assert_array_equal(merged[0], whole[0])
    np.testing.assert_array_equal(merged[1], whole[1])
    # faiss padding (-1) sorts after every real neighbour.
    padded = merge_knn([(np.array([[0.5, np.inf]], np.float32), np.array([[4, -1]]))], 2)
    np.testing.assert_array_equal(padded[1], [[4, -1]])


def test_topk_agreement():
    a = np.array([[1, 2, 3, 4], [5, 6, 7, 8]])
    assert topk_agreement(a, a) == 1.0
    assert topk_agreement(a, a[:, ::-1]) == 1.0  # order does not matter
    assert topk_agreement(a, a + 100) == 0.0
    b = np.array([[1, 2, 9, 10], [8, -1, -1, 5]])
    assert topk_agreement(a, b) == pytest.approx((2 / 4 + 2 / 4) / 2)
    # -1 is "missing", never shared, even when both sides miss.
    assert topk_agreement(np.array([[-1, 3]]), np.array([[-1, 3]])) == 0.5
    # Rows do not leak into each other.
    assert topk_agreement(np.array([[1], [2]]), np.array([[2], [1]])) == 0.0
    with pytest.raises(ValueError):
        topk_agreement(a, a[:, :2])
