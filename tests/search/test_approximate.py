"""Approximate faiss indexes against the exact top-k: recall, seeded training, defaults and
errors."""

from __future__ import annotations

import numpy as np
import pytest
from knn_helpers import clustered, unit_vectors

from vprflow.search.approximate import ivf_flat_knn, ivf_pq_knn
from vprflow.search.exact import exact_knn
from vprflow.search.indexes import SEARCH_INDEXES, search_index
from vprflow.search.topk import topk_agreement


@pytest.mark.parametrize(
    ("index", "params", "least_recall"),
    [
        ("ivf_flat", {"nlist": 16, "nprobe": 4}, 0.8),
        ("ivf_pq", {"nlist": 8, "nprobe": 4, "m": 8, "nbits": 6}, 0.3),
        ("hnsw", {"M": 16, "ef_search": 64}, 0.8),
    ],
)
def test_approximate_indexes(index, params, least_recall):
    rng = np.random.default_rng(19)
    centres = unit_vectors(rng, 20, 32)
    database, queries = clustered(rng, 3000, 32, centres), clustered(rng, 100, 32, centres)
    _, truth = exact_knn(database, queries, 10, device="cpu")
    distances, indices = SEARCH_INDEXES[index].search(database, queries, 10, params)
    assert distances.shape == indices.shape == (100, 10)
    assert distances.dtype == np.float32 and indices.dtype == np.int64
    assert np.all((indices >= -1) & (indices < len(database)))
    assert topk_agreement(indices, truth) > least_recall
    # Seeded training: a second build gives the same answer.
    if index != "hnsw":
        again = SEARCH_INDEXES[index].search(database, queries, 10, params)
        np.testing.assert_array_equal(again[1], indices)


def test_faiss_knn_defaults_and_errors():
    rng = np.random.default_rng(23)
    database, queries = unit_vectors(rng, 400, 16), unit_vectors(rng, 5, 16)
    distances, indices = ivf_flat_knn(database, queries, 500)
    assert distances.shape == indices.shape == (5, 400)  # k' = min(k, Nd)
    with pytest.raises(ValueError, match="'ivf_hnsw'"):
        search_index("ivf_hnsw")
    with pytest.raises(ValueError, match="nprobes"):
        SEARCH_INDEXES["ivf_flat"].search(database, queries, 5, {"nprobes": 3})
    with pytest.raises(ValueError, match="nlist"):
        SEARCH_INDEXES["flat"].search(database, queries, 5, {"nlist": 3})
    with pytest.raises(ValueError, match="divide"):
        ivf_pq_knn(database, queries, 5, m=3, nbits=4)
