"""Exhaustive nearest-neighbour retrieval with faiss, and SegVLAD image voting
(docs/methods.md §5, §8)."""

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


VOTE_RANKINGS = ("published", "all_images")


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
    min and max over all lists (in float32, as the published code does it on faiss's
    float32 output); the score of reference image ``r`` for query image ``q`` is the
    sum of normalised similarities of every (segment of ``q``, retrieved segment of
    ``r``) pair, accumulated in float64 in the published order (rank by rank, query
    segments in order within a rank) so that exact ties come out as published.
    Returns ``[n_query, n_ref]`` float64.
    """
    votes = _votes_rank_major(indices, query_image_of_segment, ref_image_of_segment)
    return _add_votes(distances, votes, n_query, n_ref)


def _add_votes(distances, votes, n_query: int, n_ref: int) -> np.ndarray:
    rows, cols, order = votes
    scores = np.zeros((n_query, n_ref), dtype=np.float64)
    np.add.at(scores, (rows[order], cols[order]), _vote_weights(distances).reshape(-1)[order])
    return scores


def _vote_weights(distances: np.ndarray) -> np.ndarray:
    similarity = np.float32(2.0) - np.asarray(distances, dtype=np.float32)
    if similarity.size == 0:
        return similarity.astype(np.float64)
    low, high = similarity.min(), similarity.max()
    span = high - low
    if span > 0:
        return ((similarity - low) / span).astype(np.float64)
    return np.ones_like(similarity, dtype=np.float64)


def _votes_rank_major(indices, query_image_of_segment, ref_image_of_segment):
    """Every (query image, reference image) vote as flat arrays ``[Sq * k]`` plus the
    permutation that reads them query image by query image, rank by rank, query
    segments in order within a rank."""
    n_segments, k = indices.shape
    rows = np.repeat(np.asarray(query_image_of_segment), k)
    cols = np.asarray(ref_image_of_segment)[indices.reshape(-1)]
    rank = np.tile(np.arange(k), n_segments)
    segment = np.repeat(np.arange(n_segments), k)
    return rows, cols, np.lexsort((segment, rank, rows))


def vote_ranking(
    distances: np.ndarray,
    indices: np.ndarray,
    query_image_of_segment: np.ndarray,
    ref_image_of_segment: np.ndarray,
    n_query: int,
    n_ref: int,
    top: int,
    mode: str = "published",
) -> np.ndarray:
    """Reference images per query image by voted score: ``[n_query, top]`` int64.

    ``mode="published"`` (SegVLAD's ``max_seg_topk_wt_borda_Im``): only images that
    received at least one vote are ranked; equal scores keep the order in which the
    images first appear when the retrieved lists are read rank by rank (all query
    segments' first neighbours, then their second, ...). A query with fewer than
    ``top`` voted images has its row padded with ``-1`` (never a positive, so a missing
    rank counts as a miss). ``mode="all_images"``: every reference image is ranked,
    ties (unvoted images included, score 0) by increasing index.
    """
    if mode not in VOTE_RANKINGS:
        raise ValueError(f"unknown vote ranking {mode!r}; expected one of {VOTE_RANKINGS}")
    votes = _votes_rank_major(indices, query_image_of_segment, ref_image_of_segment)
    scores = _add_votes(distances, votes, n_query, n_ref)
    top = min(top, n_ref)
    if mode == "all_images":
        return rank_by_score(scores)[:, :top].astype(np.int64)
    rows, cols, order = votes
    first_seen = np.full((n_query, n_ref), np.iinfo(np.int64).max, dtype=np.int64)
    # Position of each vote in its query's rank-major reading; the minimum per image is
    # where it first appears.
    position = np.empty(len(order), dtype=np.int64)
    position[order] = np.arange(len(order))
    np.minimum.at(first_seen, (rows, cols), position)
    ranking = np.full((n_query, top), -1, dtype=np.int64)
    for q in range(n_query):
        voted = np.flatnonzero(first_seen[q] != np.iinfo(np.int64).max)
        best = voted[np.lexsort((first_seen[q, voted], -scores[q, voted]))][:top]
        ranking[q, : len(best)] = best
    return ranking


def image_of_segment(offsets: np.ndarray) -> np.ndarray:
    """Owner image of every row of a ragged array with ``offsets [n + 1]`` -> ``[offsets[-1]]``."""
    return np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
