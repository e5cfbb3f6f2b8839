"""Exhaustive squared-L2 search with faiss ``IndexFlatL2``: the published search of every
method (global descriptors, docs/methods.md §8; SegVLAD's segments, §5) and the
reference the other searches of :mod:`vprflow.search` are measured against.

Imports no torch: stages that search only this way start without it.
"""

from __future__ import annotations

import numpy as np

from vprflow.search.inputs import empty_result, faiss_inputs


def flat_knn(database: np.ndarray, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Exact squared-L2 k-NN: ``database [Nd, D]``, ``queries [Nq, D]`` ->
    ``(distances [Nq, k'] float32, indices [Nq, k'] int64)`` with ``k' = min(k, Nd)``,
    nearest first."""
    import faiss

    database, queries, k_out = faiss_inputs(database, queries, k)
    if k_out == 0 or len(queries) == 0:
        return empty_result(len(queries), k_out)
    index = faiss.IndexFlatL2(database.shape[1])
    index.add(database)
    distances, indices = index.search(queries, k_out)
    return distances, indices.astype(np.int64, copy=False)
