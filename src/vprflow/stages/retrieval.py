"""A method's retrieval, as every stage after it reads it: each query's references
ranked from the descriptors store (and the segment search, for a per-segment method),
and the top-1 matches the precision-recall metrics judge. Recall, matches, the pairs
export and the figures rank through here, so they rank alike."""

from __future__ import annotations

import time

import numpy as np

from vprflow.core import stores
from vprflow.evaluation.precision_recall import top1_confidence
from vprflow.evaluation.recall import correct_at, counted_queries
from vprflow.search.flat import flat_knn, ranked_distances
from vprflow.search.voting import image_of_segment, scored_vote_ranking
from vprflow.stages.readers import Dataset, read_search


def retrieve(
    dataset: Dataset,
    descriptors_path: str,
    depth: int,
    search_path: str | None = None,
    vote_ranking: str | None = None,
) -> tuple[np.ndarray, np.ndarray, str]:
    """Each query's first ``depth`` references: ``(ranking [Nq, d], scores [Nq, d],
    score kind)``, ``d`` = ``depth`` capped at the references. Per-segment descriptors
    are ranked by voting over the segment lists of the ``search`` stage
    (``search_path``); scores are votes (higher is better). Global ones by faiss's exact
    search (the published one, whose float32 order decides the ranking); scores are each
    ranked pair's squared L2 distance in float64 (lower is better), the same on every
    machine for the same ranking."""

    group = stores.open_store(descriptors_path)
    n_ref, n_query = dataset.n_reference, dataset.n_query
    depth = min(depth, n_ref)
    if group.attrs["kind"] != "segments":
        vectors = np.asarray(group["descriptors"][...])
        _, ranking = flat_knn(vectors[:n_ref], vectors[n_ref:], depth)
        return ranking, ranked_distances(vectors[:n_ref], vectors[n_ref:], ranking), "squared_l2"
    if search_path is None:
        raise ValueError(f"{descriptors_path}: per-segment descriptors need a search input")
    offsets = np.asarray(group["descriptors_offsets"][...])
    split = int(offsets[n_ref])
    owner = image_of_segment(offsets)
    distances, indices = read_search(search_path)
    ranking, scores = scored_vote_ranking(
        distances,
        indices,
        owner[split:] - n_ref,
        owner[:split],
        n_query,
        n_ref,
        depth,
        vote_ranking,
    )
    return ranking, scores, "votes"


def timed_retrieve(
    dataset: Dataset,
    descriptors_path: str,
    depth: int,
    search_path: str | None = None,
    vote_ranking: str | None = None,
) -> tuple[tuple[np.ndarray, np.ndarray, str], float]:
    """:func:`retrieve`'s result, and the milliseconds it took per query."""
    started = time.perf_counter()
    found = retrieve(dataset, descriptors_path, depth, search_path, vote_ranking)
    return found, 1000 * (time.perf_counter() - started) / max(dataset.n_query, 1)


def top1_matches(
    ranking: np.ndarray,
    scores: np.ndarray,
    score_kind: str,
    truth: list[np.ndarray],
    counted: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """What the precision-recall metrics judge, over the ``counted [Nq]`` queries:
    ``(confidence, correct, has_positive)``, each ``[n counted]``, of every query's
    top-1 match (:mod:`vprflow.evaluation.precision_recall`); None when no counted query has a
    correct top-1 match, where VPR-Bench's recall is 0 / 0."""

    counted = np.asarray(counted, dtype=bool)
    correct = (correct_at(ranking, truth) == 0)[counted]
    confidence = top1_confidence(scores, score_kind, ranking)[counted]
    if not (correct & np.isfinite(confidence)).any():
        return None
    has_positive = counted_queries(truth, "with_positives")[counted]
    return confidence, correct, has_positive
