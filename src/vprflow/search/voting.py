"""SegVLAD's similarity-weighted image voting (docs/methods.md §5): each query segment's
retrieved reference segments (the ``search`` stage's lists) vote for their images, and the
voted scores rank the reference images of every query image."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

VOTE_RANKINGS = ("published", "all_images")


@dataclass
class ImageScores:
    """Voted image scores, sparse: one entry per (query image, reference image) pair that
    received at least one vote, sorted by query then reference image.

    ``query``, ``ref`` ``[P]`` int64; ``score`` ``[P]`` float64; ``first_seen`` ``[P]``
    int64, the position of the pair's first vote when the retrieved lists are read
    rank-major (see :func:`segment_vote_scores`).
    """

    query: np.ndarray
    ref: np.ndarray
    score: np.ndarray
    first_seen: np.ndarray


def segment_vote_scores(
    distances: np.ndarray,
    indices: np.ndarray,
    query_image_of_segment: np.ndarray,
    ref_image_of_segment: np.ndarray,
    n_ref: int,
) -> ImageScores:
    """Similarity-weighted Borda voting of retrieved segments into image scores.

    ``distances``/``indices`` ``[Sq, k]``: each query segment's nearest reference
    segments (squared L2). Similarity ``2 - d`` is min-max normalised with the global
    min and max over all lists (in float32, as the published code does it on faiss's
    float32 output); the score of reference image ``r`` for query image ``q`` is the
    sum of normalised similarities of every (segment of ``q``, retrieved segment of
    ``r``) pair, accumulated in float64 in the published order (per query image rank by
    rank, query segments in order within a rank) so that exact ties come out as
    published. Entries with index ``-1`` (not found by an approximate index) are
    ignored. Only voted pairs are stored: memory is ``O(Sq * k)``, never
    ``n_query x n_ref``.
    """
    n_segments, k = indices.shape
    found = indices.reshape(-1) >= 0  # an approximate search may find fewer than k
    rows = np.repeat(np.asarray(query_image_of_segment, dtype=np.int64), k)[found]
    cols = np.asarray(ref_image_of_segment, dtype=np.int64)[indices.reshape(-1)[found]]
    rank = np.tile(np.arange(k), n_segments)[found]
    segment = np.repeat(np.arange(n_segments), k)[found]
    reading = np.lexsort((segment, rank, rows))
    pair = rows[reading] * n_ref + cols[reading]
    keys, first_seen, inverse = np.unique(pair, return_index=True, return_inverse=True)
    # bincount adds in array order, i.e. in the published reading order.
    weights = _vote_weights(np.asarray(distances).reshape(-1)[found])[reading]
    score = np.bincount(inverse.reshape(-1), weights=weights, minlength=len(keys))
    return ImageScores(keys // n_ref, keys % n_ref, score, first_seen.astype(np.int64))


def _vote_weights(distances: np.ndarray) -> np.ndarray:
    similarity = np.float32(2.0) - np.asarray(distances, dtype=np.float32)
    if similarity.size == 0:
        return similarity.astype(np.float64)
    low, high = similarity.min(), similarity.max()
    span = high - low
    if span > 0:
        return ((similarity - low) / span).astype(np.float64)
    return np.ones_like(similarity, dtype=np.float64)


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
    """Reference images per query image by voted score: ``[n_query, top]`` int64 (the
    ranking of :func:`scored_vote_ranking`)."""
    return scored_vote_ranking(
        distances, indices, query_image_of_segment, ref_image_of_segment, n_query, n_ref, top, mode
    )[0]


def scored_vote_ranking(
    distances: np.ndarray,
    indices: np.ndarray,
    query_image_of_segment: np.ndarray,
    ref_image_of_segment: np.ndarray,
    n_query: int,
    n_ref: int,
    top: int,
    mode: str = "published",
) -> tuple[np.ndarray, np.ndarray]:
    """Reference images per query image by voted score, and their scores:
    ``(ranking [n_query, top] int64, scores [n_query, top] float64)``.

    ``mode="published"`` (SegVLAD's ``max_seg_topk_wt_borda_Im``): only images that
    received at least one vote are ranked; equal scores keep the order in which the
    images first appear when the retrieved lists are read rank by rank (all query
    segments' first neighbours, then their second, ...). A query with fewer than
    ``top`` voted images has its row padded with ``-1`` (never a positive, so a missing
    rank counts as a miss). ``mode="all_images"``: every reference image is ranked,
    ties (unvoted images included, score 0) by increasing index.

    Works on the sparse scores: sorts only voted pairs, never a full row. Scores of
    unvoted images (``all_images``) and of padding (rank -1) are 0.
    """
    if mode not in VOTE_RANKINGS:
        raise ValueError(f"unknown vote ranking {mode!r}; expected one of {VOTE_RANKINGS}")
    votes = segment_vote_scores(
        distances, indices, query_image_of_segment, ref_image_of_segment, n_ref
    )
    top = min(top, n_ref)
    ranking = np.full((n_query, top), -1, dtype=np.int64)
    scores = np.zeros((n_query, top))
    if mode == "published":
        order = np.lexsort((votes.first_seen, -votes.score, votes.query))
    else:  # zero scores tie with unvoted images: they are filled in by index below
        positive = np.flatnonzero(votes.score > 0)
        order = positive[
            np.lexsort((votes.ref[positive], -votes.score[positive], votes.query[positive]))
        ]
    query, ref = votes.query[order], votes.ref[order]
    starts = np.searchsorted(query, np.arange(n_query))
    place = np.arange(len(order)) - starts[query]
    kept = place < top
    ranking[query[kept], place[kept]] = ref[kept]
    scores[query[kept], place[kept]] = votes.score[order][kept]
    if mode == "all_images":
        counts = np.bincount(query, minlength=n_query)
        for q in np.flatnonzero(counts < top):
            ranked = ranking[q, : counts[q]]
            # The first (top - counts) images by index that are not ranked yet.
            candidates = np.arange(min(n_ref, top + counts[q]))
            ranking[q, counts[q] :] = candidates[~np.isin(candidates, ranked)][: top - counts[q]]
    return ranking, scores


def image_of_segment(offsets: np.ndarray) -> np.ndarray:
    """Owner image of every row of a ragged array with ``offsets [n + 1]`` -> ``[offsets[-1]]``."""
    return np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
