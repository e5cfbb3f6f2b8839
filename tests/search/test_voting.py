"""SegVLAD image voting against direct loops in float64.

Vote weights are float32 as in the published code (its min-max normalisation runs on
faiss's float32 output), the direct loops compute them the same way; sums are float64:
rtol 1e-12.
"""

from __future__ import annotations

import numpy as np
import pytest

from vprflow.search.voting import image_of_segment, segment_vote_scores, vote_ranking


def direct_vote(distances, indices, query_image, ref_image, n_query, n_ref):
    """REFERENCE.md section 2 step 8, one retrieved pair at a time."""
    weights = direct_weights(distances)
    scores = np.zeros((n_query, n_ref))
    for s in range(len(indices)):
        for j in range(indices.shape[1]):
            scores[query_image[s], ref_image[indices[s, j]]] += weights[s][j]
    return scores


def direct_weights(distances):
    """Min-max normalised similarities 2 - d, each step in float32 (published)."""
    two = np.float32(2.0)
    similarities = [[two - np.float32(d) for d in row] for row in distances]
    flat = [v for row in similarities for v in row]
    low, high = min(flat), max(flat)
    return [[float((v - low) / (high - low)) for v in row] for row in similarities]


def published_ranking(distances, indices, query_image, ref_image, n_query, top):
    """The published ``max_seg_topk_wt_borda_Im`` with plain dicts: per query image,
    read its segments' lists rank by rank, add each normalised similarity to the
    retrieved segment's image, sort by score (Python's stable sort keeps first-seen
    order among equal scores)."""
    weights = direct_weights(distances)
    rankings = []
    for q in range(n_query):
        segments = [s for s in range(len(indices)) if query_image[s] == q]
        scores = {}
        for rank in range(indices.shape[1]):
            for s in segments:
                image = int(ref_image[indices[s, rank]])
                scores[image] = scores.get(image, 0.0) + weights[s][rank]
        rankings.append(sorted(scores, key=lambda image: scores[image], reverse=True)[:top])
    return rankings


def rank_by_score(scores: np.ndarray) -> np.ndarray:
    """Reference indices by decreasing score, ties by increasing index: ``[Nq, Nr]``."""
    return np.argsort(-scores, axis=1, kind="stable")


def dense_scores(distances, indices, query_image, ref_image, n_query, n_ref):
    """The sparse voted scores as a dense ``[n_query, n_ref]`` array (0 where unvoted)."""
    votes = segment_vote_scores(distances, indices, query_image, ref_image, n_ref)
    assert (np.diff(votes.query * n_ref + votes.ref) > 0).all()  # sorted, one per pair
    scores = np.zeros((n_query, n_ref))
    scores[votes.query, votes.ref] = votes.score
    return scores


def vote_problem(seed, n_query=4, n_ref=6, segments_per_ref=(3, 0, 5, 2, 4, 1), k=5):
    rng = np.random.default_rng(seed)
    ref_offsets = np.concatenate([[0], np.cumsum(segments_per_ref)])
    query_offsets = np.concatenate([[0], np.cumsum(rng.integers(1, 5, n_query))])
    n_ref_segments, n_query_segments = ref_offsets[-1], query_offsets[-1]
    indices = np.stack(
        [rng.choice(n_ref_segments, k, replace=False) for _ in range(n_query_segments)]
    )
    distances = np.sort(rng.uniform(0.2, 3.5, (n_query_segments, k)), axis=1).astype(np.float32)
    return distances, indices, image_of_segment(query_offsets), image_of_segment(ref_offsets)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_segment_vote_scores_match_direct_loop(seed):
    distances, indices, query_image, ref_image = vote_problem(seed)
    scores = dense_scores(distances, indices, query_image, ref_image, 4, 6)
    expected = direct_vote(distances, indices, query_image, ref_image, 4, 6)
    assert scores.shape == (4, 6) and scores.dtype == np.float64
    np.testing.assert_allclose(scores, expected, rtol=1e-12, atol=1e-12)
    # Reference image 1 has no segments: it can never receive a vote.
    np.testing.assert_array_equal(scores[:, 1], 0.0)
    # The global best pair weighs 1, the global worst 0: total weight is bounded.
    assert scores.sum() <= indices.size


def test_segment_vote_normalises_with_global_min_and_max():
    # Two query images with one segment each; min-max over both lists together.
    distances = np.array([[0.0, 1.0], [2.0, 4.0]], np.float32)  # similarities 2, 1, 0, -2
    indices = np.array([[0, 1], [1, 0]])
    scores = dense_scores(distances, indices, np.array([0, 1]), np.array([0, 1]), 2, 2)
    np.testing.assert_allclose(scores, [[1.0, 0.75], [0.0, 0.5]])


def test_segment_vote_with_equal_distances_counts_every_pair_once():
    distances = np.full((3, 2), 0.5, np.float32)
    indices = np.array([[0, 1], [1, 2], [2, 0]])
    scores = dense_scores(distances, indices, np.array([0, 0, 1]), np.array([0, 0, 1]), 2, 2)
    np.testing.assert_allclose(scores, [[3.0, 1.0], [1.0, 1.0]])


def test_rank_by_score_breaks_ties_by_index():
    rng = np.random.default_rng(0)
    scores = rng.integers(0, 4, (20, 9)).astype(np.float64)  # many ties
    ranking = rank_by_score(scores)
    for q in range(len(scores)):
        expected = sorted(range(scores.shape[1]), key=lambda r, q=q: (-scores[q, r], r))
        np.testing.assert_array_equal(ranking[q], expected)


@pytest.mark.parametrize(
    "counts", [[3, 0, 2], [0, 0], [1], [0, 4, 0, 0, 1], []], ids=lambda c: str(c)
)
def test_image_of_segment_matches_direct_loop(counts):
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    expected = [image for image, count in enumerate(counts) for _ in range(count)]
    np.testing.assert_array_equal(image_of_segment(offsets), expected)


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4])
@pytest.mark.parametrize("quantised", [False, True], ids=["distinct", "ties"])
def test_vote_ranking_matches_the_published_loop(seed, quantised):
    distances, indices, query_image, ref_image = vote_problem(seed, n_ref=6, k=3)
    if quantised:
        # Few distinct distances, so many images tie on score: the order among them
        # is decided by first appearance alone.
        distances = np.round(distances * 2) / 2
    top = 6
    ranking = vote_ranking(distances, indices, query_image, ref_image, 4, 6, top)
    expected = published_ranking(distances, indices, query_image, ref_image, 4, top)
    assert ranking.shape == (4, top) and ranking.dtype == np.int64
    for q in range(4):
        row = ranking[q]
        assert row[: len(expected[q])].tolist() == expected[q]
        # Only voted images are ranked: the rest of the row is padding.
        assert (row[len(expected[q]) :] == -1).all()
    # Reference image 1 has no segments, so no query can rank it.
    assert not (ranking == 1).any()


def test_vote_ranking_breaks_ties_by_first_appearance_not_index():
    # One query image with two segments; every distance equal, so every vote weighs 1.
    # Rank 0 retrieves images 3 and 2, rank 1 images 0 and 2: image 2 gets two votes,
    # then 3 (seen first) before 0.
    distances = np.zeros((2, 2), np.float32)
    indices = np.array([[3, 0], [2, 2]])
    ranking = vote_ranking(distances, indices, np.array([0, 0]), np.arange(4), 1, 4, 4)
    assert ranking.tolist() == [[2, 3, 0, -1]]
    full = vote_ranking(distances, indices, np.array([0, 0]), np.arange(4), 1, 4, 4, "all_images")
    assert full.tolist() == [[2, 0, 3, 1]]


def test_vote_ranking_all_images_is_rank_by_score():
    distances, indices, query_image, ref_image = vote_problem(3)
    scores = dense_scores(distances, indices, query_image, ref_image, 4, 6)
    ranking = vote_ranking(distances, indices, query_image, ref_image, 4, 6, 5, "all_images")
    np.testing.assert_array_equal(ranking, rank_by_score(scores)[:, :5])


def test_vote_ranking_rejects_an_unknown_mode():
    distances, indices, query_image, ref_image = vote_problem(0)
    with pytest.raises(ValueError, match="'borda'"):
        vote_ranking(distances, indices, query_image, ref_image, 4, 6, 5, "borda")


@pytest.mark.parametrize("mode", ["published", "all_images"])
def test_voting_never_allocates_query_by_reference_scores(mode):
    """1,000 query images against 10^9 reference images: a dense score matrix would be
    8 TB; the sparse votes are a few thousand pairs."""
    rng = np.random.default_rng(0)
    n_query, n_ref, k = 1000, 10**9, 5
    query_image = np.repeat(np.arange(n_query), 2)
    ref_image = rng.integers(0, n_ref, 50)  # 50 reference segments of far-apart images
    indices = rng.integers(0, 50, (len(query_image), k))
    distances = np.sort(rng.uniform(0, 2, indices.shape), axis=1).astype(np.float32)
    ranking = vote_ranking(distances, indices, query_image, ref_image, n_query, n_ref, 20, mode)
    assert ranking.shape == (n_query, 20)
    voted = ranking[ranking >= 0]
    if mode == "published":
        assert np.isin(voted, ref_image).all()
    else:
        assert (ranking >= 0).all()
