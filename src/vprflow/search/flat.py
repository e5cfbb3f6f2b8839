"""Exhaustive squared-L2 search with faiss ``IndexFlatL2``: the published search of every
method (global descriptors, docs/methods.md §8; SegVLAD's segments, §5) and the
reference the other searches of :mod:`vprflow.search` are measured against.

Imports no torch: stages that search only this way start without it (faiss is named
with ``lazy_import``: planning reads :data:`vprflow.search.indexes.INDEXES`, which holds
:func:`flat_knn`).
"""

from __future__ import annotations

import numpy as np

from vprflow.core.lazy import lazy_import
from vprflow.search.inputs import as_matrix, empty_result, faiss_inputs

faiss = lazy_import("faiss")


def flat_knn(database: np.ndarray, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Exact squared-L2 k-NN: ``database [Nd, D]``, ``queries [Nq, D]`` ->
    ``(distances [Nq, k'] float32, indices [Nq, k'] int64)`` with ``k' = min(k, Nd)``,
    nearest first."""
    database, queries, k_out = faiss_inputs(database, queries, k)
    if k_out == 0 or len(queries) == 0:
        return empty_result(len(queries), k_out)
    index = faiss.IndexFlatL2(database.shape[1])
    index.add(database)
    distances, indices = index.search(queries, k_out)
    return distances, indices.astype(np.int64, copy=False)


def ranked_distances(database: np.ndarray, queries: np.ndarray, ranking: np.ndarray) -> np.ndarray:
    """The squared L2 distance of every ranked pair, each taken in float64 and rounded
    once: ``database [Nd, D]``, ``queries [Nq, D]``, ``ranking [Nq, k]`` (database
    indices) -> ``[Nq, k]`` float32.

    faiss's own distances are float32 products through its BLAS, whose rounding moves
    with the kernel: on roadscene's unnormalised SNSM vectors by up to 0.1 in 300, enough
    to reorder queries by their top-1 distance (the precision-recall summary's
    confidence) from one kernel to the next. These depend on the ranking alone."""
    database = as_matrix(database, "database")
    queries = as_matrix(queries, "queries")
    ranking = np.asarray(ranking)
    out = np.empty(ranking.shape, dtype=np.float32)
    # Queries per block: a float64 copy of [rows, k, D] of about 64 MiB.
    rows = max(1, (1 << 23) // max(ranking.shape[1] * database.shape[1], 1))
    for start in range(0, len(ranking), rows):
        block = ranking[start : start + rows]
        difference = np.asarray(database[block], dtype=np.float64) - np.asarray(
            queries[start : start + rows, None], dtype=np.float64
        )
        out[start : start + rows] = (difference * difference).sum(axis=2)
    return out
