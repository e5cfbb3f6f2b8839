"""Recall@N over queries that have at least one positive (docs/methods.md §8)."""

from __future__ import annotations

import numpy as np


def correct_at(ranking: np.ndarray, truth: list[np.ndarray]) -> np.ndarray:
    """Rank (0-based) of the first correct reference per query, or -1: ``[Nq]``.

    ``ranking`` ``[Nq, k]`` reference indices, best first.
    """
    first = np.full(len(ranking), -1, dtype=np.int64)
    for q, (row, positives) in enumerate(zip(ranking, truth, strict=True)):
        hits = np.flatnonzero(np.isin(row, positives))
        if len(hits):
            first[q] = hits[0]
    return first


def recall_at(ranking: np.ndarray, truth: list[np.ndarray], ns: list[int]) -> dict[int, float]:
    """Fraction of queries with a positive whose top ``n`` contains one, for each ``n``."""
    evaluated = np.array([len(t) > 0 for t in truth])
    if not evaluated.any():
        raise ValueError("no query has a ground-truth positive: recall is undefined")
    first = correct_at(ranking, truth)[evaluated]
    return {n: float(np.mean((first >= 0) & (first < n))) for n in ns}
