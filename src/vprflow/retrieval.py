"""Exhaustive nearest-neighbour retrieval with faiss, and SegVLAD image voting."""

from __future__ import annotations

import numpy as np


def search(database: np.ndarray, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Exact squared-L2 k-NN: ``database [Nd, D]``, ``queries [Nq, D]`` ->
    ``(distances [Nq, k'], indices [Nq, k'])`` with ``k' = min(k, Nd)``, nearest first."""
    import faiss

    database = np.ascontiguousarray(database, dtype=np.float32)
    queries = np.ascontiguousarray(queries, dtype=np.float32)
    k = min(k, len(database))
    index = faiss.IndexFlatL2(database.shape[1])
    index.add(database)
    distances, indices = index.search(queries, k)
    return distances, indices


def rank_by_score(scores: np.ndarray) -> np.ndarray:
    """Reference indices by decreasing score, ties by increasing index: ``[Nq, Nr]``."""
    return np.argsort(-scores, axis=1, kind="stable")


def global_ranking(reference: np.ndarray, query: np.ndarray, top: int) -> np.ndarray:
    """Top-``top`` reference images per query for global descriptors ``[N, D]``."""
    _, indices = search(reference, query, top)
    return indices


def segment_vote_scores(
    distances: np.ndarray,
    indices: np.ndarray,
    query_image_of_segment: np.ndarray,
    ref_image_of_segment: np.ndarray,
    n_query: int,
    n_ref: int,
) -> np.ndarray:
    """Similarity-weighted Borda voting of retrieved segments into image scores.

    ``distances``/``indices`` ``[Sq, k]``: each query segment's nearest reference
    segments (squared L2). Similarity ``2 - d`` is min-max normalised with the global
    min and max over all lists; the score of reference image ``r`` for query image
    ``q`` is the sum of normalised similarities of every (segment of ``q``, retrieved
    segment of ``r``) pair. Returns ``[n_query, n_ref]`` float64.
    """
    similarity = 2.0 - distances.astype(np.float64)
    low, high = similarity.min(initial=np.inf), similarity.max(initial=-np.inf)
    span = high - low
    weights = (similarity - low) / span if span > 0 else np.ones_like(similarity)
    scores = np.zeros((n_query, n_ref), dtype=np.float64)
    rows = np.repeat(query_image_of_segment, indices.shape[1])
    cols = ref_image_of_segment[indices.reshape(-1)]
    np.add.at(scores, (rows, cols), weights.reshape(-1))
    return scores


def image_of_segment(offsets: np.ndarray) -> np.ndarray:
    """Owner image of every row of a ragged array with ``offsets [n + 1]`` -> ``[offsets[-1]]``."""
    return np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
