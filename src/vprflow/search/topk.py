"""Top-k lists of several searches: merged into one (the shards of a search) and compared
(an approximate or low-precision search against an exact one).

A list is ``(distances [Nq, k] float32, indices [Nq, k] int64)``, each row ordered by
(distance, index), so exact ties go to the lower index; ``-1`` is a missing neighbour
(faiss's padding of rows that found fewer than k) and sorts after every real one.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from vprflow.search.inputs import non_negative_int

# An index that sorts after every real one: padding of rows that have seen fewer than k
# items, and the sort key of missing (-1) neighbours.
NO_INDEX = np.iinfo(np.int64).max


def merge_knn(
    parts: Sequence[tuple[np.ndarray, np.ndarray]], k: int
) -> tuple[np.ndarray, np.ndarray]:
    """Merge per-shard results into one top-k: ``parts`` of ``(distances [Nq, k_s],
    indices [Nq, k_s])`` whose indices already point into the full database ->
    ``(distances [Nq, k'], indices [Nq, k'])``, ``k' = min(k, sum k_s)``, sorted by
    (distance, index); ``-1`` indices (faiss's padding) sort last. One part gives its
    rows in that order."""
    if not parts:
        raise ValueError("merge_knn needs at least one part")
    dist = np.concatenate([np.asarray(d, dtype=np.float32) for d, _ in parts], axis=1)
    idx = np.concatenate([np.asarray(i, dtype=np.int64) for _, i in parts], axis=1)
    k_out = min(non_negative_int("k", k), dist.shape[1])
    missing = idx < 0
    order = np.lexsort((np.where(missing, NO_INDEX, idx), dist, missing), axis=-1)[:, :k_out]
    return np.take_along_axis(dist, order, 1), np.take_along_axis(idx, order, 1)


def topk_agreement(indices_a: np.ndarray, indices_b: np.ndarray) -> float:
    """Mean over rows of the fraction of the top-k set shared: ``[N, k]`` x ``[N, k]`` -> float.

    Order within a row does not matter; ``-1`` (missing) never counts as shared. Rows are
    assumed to hold distinct indices. Vacuously 1.0 when there are no rows or k is 0.
    """
    a = np.asarray(indices_a, dtype=np.int64)
    b = np.asarray(indices_b, dtype=np.int64)
    if a.ndim != 2 or a.shape != b.shape:
        raise ValueError(f"expected two [N, k] arrays of one shape, got {a.shape} and {b.shape}")
    n, k = a.shape
    if n == 0 or k == 0:
        return 1.0
    # One key per (row, index): a set test over all rows at once. -1 in b maps to the last
    # key of the previous row's span, which no valid index of a can take.
    span = int(max(a.max(), b.max())) + 2
    offset = np.arange(n, dtype=np.int64)[:, None] * span
    shared = np.isin(a + offset, b + offset) & (a >= 0)
    return float(shared.sum(1).mean() / k)
