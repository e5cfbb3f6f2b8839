"""Recall@N and mAP@N of rankings against a ground truth (docs/methods.md §8).

Which queries count is the ``denominator``: ``"with_positives"`` (the published SegVLAD
code skips queries that have no positive) or ``"all"`` (AnyLoc's ``get_top_k_recall``
and VPR-methods-evaluation divide by every query, so a query without a positive is a
miss).
"""

from __future__ import annotations

import numpy as np

DENOMINATORS = ("with_positives", "all")

# What a method costs, as the results table states it beside its recall.
COST_COLUMNS = ("descriptor_bytes_per_image", "search_ms_per_query", "rerank_ms_per_query")


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


def queries_without_positive(truth: list[np.ndarray]) -> np.ndarray:
    """int64 ``[n]``: the queries with no positive, in order. Under either denominator
    the table says how many (``with_positives`` leaves them out, ``all`` counts them as
    misses): a query that lost its positives to a damaged position or index must not
    leave the count without a word."""
    return np.flatnonzero([len(t) == 0 for t in truth]).astype(np.int64)


def counted_queries(truth: list[np.ndarray], denominator: str = "with_positives") -> np.ndarray:
    """bool ``[Nq]``: the queries a metric averages over."""
    if denominator not in DENOMINATORS:
        raise ValueError(f"unknown denominator {denominator!r}; expected one of {DENOMINATORS}")
    has_positive = np.array([len(t) > 0 for t in truth], dtype=bool)
    if not has_positive.any():
        raise ValueError("no query has a ground-truth positive: recall is undefined")
    return has_positive if denominator == "with_positives" else np.ones_like(has_positive)


def recall_at(
    ranking: np.ndarray, truth: list[np.ndarray], ns: list[int], denominator: str = "with_positives"
) -> dict[int, float]:
    """Fraction of the counted queries whose top ``n`` contains a positive, per ``n``."""
    counted = counted_queries(truth, denominator)
    first = correct_at(ranking, truth)[counted]
    return {n: float(np.mean((first >= 0) & (first < n))) for n in ns}


def average_precision_at(ranking: np.ndarray, truth: list[np.ndarray], n: int) -> np.ndarray:
    """AP of each query's top ``n``, as the published Revisit-Anything ``calculate_ap``:
    the mean of precision@i over the ranks i <= n that hold a positive, divided by the
    number of positives retrieved in the top n (not by all positives); 0 when none is.
    Returns float64 ``[Nq]``."""
    out = np.zeros(len(ranking))
    for q, (row, positives) in enumerate(zip(ranking, truth, strict=True)):
        relevant = np.isin(row[:n], positives) & (row[:n] >= 0)
        if relevant.any():
            hits = np.cumsum(relevant)
            ranks = np.arange(1, len(relevant) + 1)
            out[q] = np.sum((hits / ranks)[relevant]) / relevant.sum()
    return out


def map_at(
    ranking: np.ndarray, truth: list[np.ndarray], ns: list[int], denominator: str = "with_positives"
) -> dict[int, float]:
    """Mean of :func:`average_precision_at` over the counted queries, per ``n``."""
    counted = counted_queries(truth, denominator)
    return {n: float(np.mean(average_precision_at(ranking, truth, n)[counted])) for n in ns}
