"""Re-ranking by local patch matches (vprflow.evaluation.rerank) against direct loops in float64.

Mutual nearest neighbours: float32 inputs, the direct double loop computes every dot
product in float64 and breaks ties by the lower index; similarities agree to 1e-6. The
exact-tie cases use small integer descriptors, whose dot products are exact in float32
whatever the summation order, so float32 and float64 see the same ties. RANSAC: synthetic
correspondences from a known homography plus uniform outliers.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from synthetic import make_dataset
from workflow_helpers import REPO, run_stage, toy_config

from vprflow.core import stores
from vprflow.evaluation import rerank as rerank_module
from vprflow.evaluation.rerank import (
    candidate_pairs,
    mnn_pair_scores,
    mnn_score,
    mutual_nearest_neighbours,
    pair_scorer,
    patch_centres,
    ransac_inliers,
    ransac_pair_scores,
    rerank,
)
from vprflow.planning.config import validate_config
from vprflow.planning.plan import build_plan

SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"


def stage_scores(query, candidates, grid, patch, method, **options) -> np.ndarray:
    """A query's scores as the ``matches`` and ``rerank`` stages compute them: its
    candidates' pairs, scored by the re-ranker (its options checked first)."""
    score = pair_scorer(method, options, grid, patch)
    return score(candidate_pairs(query, candidates))


def unit_rows(rng: np.random.Generator, n: int, dim: int) -> np.ndarray:
    x = rng.normal(size=(n, dim))
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def direct_mnn(query: np.ndarray, candidate: np.ndarray):
    """Pairs ``(i, j, similarity)`` by a double loop in float64; on ties the lower index
    wins (only a strictly larger similarity replaces the best so far)."""
    q, c = query.astype(np.float64), candidate.astype(np.float64)
    sim = [[float(np.dot(q[i], c[j])) for j in range(len(c))] for i in range(len(q))]
    forward = []
    for i in range(len(q)):
        best = 0
        for j in range(1, len(c)):
            if sim[i][j] > sim[i][best]:
                best = j
        forward.append(best)
    backward = []
    for j in range(len(c)):
        best = 0
        for i in range(1, len(q)):
            if sim[i][j] > sim[best][j]:
                best = i
        backward.append(best)
    pairs = [
        (i, forward[i], sim[i][forward[i]]) for i in range(len(q)) if backward[forward[i]] == i
    ]
    return pairs


def integer_rows_with_ties(rng: np.random.Generator, n: int, dim: int) -> np.ndarray:
    """Small integer descriptors with duplicated rows, so that nearest neighbours tie."""
    x = rng.integers(-2, 3, size=(n, dim)).astype(np.float32)
    x[n // 2 :] = x[: n - n // 2]  # the second half repeats the first
    return x


def has_tie(query: np.ndarray, candidate: np.ndarray) -> bool:
    sim = query.astype(np.float64) @ candidate.astype(np.float64).T
    best_forward = (sim == sim.max(axis=1, keepdims=True)).sum(axis=1)
    best_backward = (sim == sim.max(axis=0, keepdims=True)).sum(axis=0)
    return bool((best_forward > 1).any() or (best_backward > 1).any())


def check_against_direct(query: np.ndarray, candidate: np.ndarray) -> None:
    i, j, similarity = mutual_nearest_neighbours(
        torch.from_numpy(query), torch.from_numpy(candidate)
    )
    expected = direct_mnn(query, candidate)
    assert i.dtype == np.int64 and j.dtype == np.int64
    assert list(zip(i.tolist(), j.tolist(), strict=True)) == [(a, b) for a, b, _ in expected]
    np.testing.assert_allclose(similarity, [s for _, _, s in expected], rtol=0, atol=1e-6)


@pytest.mark.parametrize("seed", range(5))
def test_mutual_nearest_neighbours_match_a_double_loop_on_random_unit_descriptors(seed):
    rng = np.random.default_rng(seed)
    query, candidate = unit_rows(rng, 23, 16), unit_rows(rng, 31, 16)
    # Some near-duplicates so that the mutual set is not only chance pairs.
    candidate[:8] = query[5:13] + 0.05 * unit_rows(rng, 8, 16)
    check_against_direct(query, candidate)


@pytest.mark.parametrize("seed", range(5))
def test_mutual_nearest_neighbours_break_exact_ties_by_the_lower_index_like_the_loop(seed):
    rng = np.random.default_rng(100 + seed)
    query, candidate = integer_rows_with_ties(rng, 14, 6), integer_rows_with_ties(rng, 18, 6)
    candidate[:4] = query[:4]
    assert has_tie(query, candidate)
    check_against_direct(query, candidate)


def test_the_lower_index_wins_a_tie_on_either_side():
    one = torch.tensor([[1.0, 0.0]])
    two = torch.tensor([[1.0, 0.0], [1.0, 0.0]])
    i, j, similarity = mutual_nearest_neighbours(one, two)
    assert (i.tolist(), j.tolist(), similarity.tolist()) == ([0], [0], [1.0])
    i, j, _ = mutual_nearest_neighbours(two, one)
    assert (i.tolist(), j.tolist()) == ([0], [0])


def test_mutual_nearest_neighbours_of_an_empty_set_are_empty():
    i, j, similarity = mutual_nearest_neighbours(torch.zeros(0, 4), torch.ones(3, 4))
    assert len(i) == len(j) == len(similarity) == 0


def test_mutual_nearest_neighbours_accept_numpy_and_return_numpy():
    rng = np.random.default_rng(7)
    query, candidate = unit_rows(rng, 9, 8), unit_rows(rng, 11, 8)
    from_numpy = mutual_nearest_neighbours(query, candidate)
    from_torch = mutual_nearest_neighbours(torch.from_numpy(query), torch.from_numpy(candidate))
    for a, b in zip(from_numpy, from_torch, strict=True):
        assert isinstance(a, np.ndarray)
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("seed", range(3))
def test_mnn_score_counts_or_sums_the_mutual_pairs_as_the_direct_formula(seed):
    rng = np.random.default_rng(200 + seed)
    query, candidate = unit_rows(rng, 20, 12), unit_rows(rng, 25, 12)
    candidate[:10] = query[:10] + 0.1 * unit_rows(rng, 10, 12)
    pairs = direct_mnn(query, candidate)
    similarities = np.array([s for _, _, s in pairs])
    assert mnn_score(query, candidate) == len(pairs)
    assert mnn_score(query, candidate, "similarity") == pytest.approx(similarities.sum(), abs=1e-5)
    cut = float(np.median(similarities))
    kept = similarities[similarities >= cut]
    assert mnn_score(query, candidate, "count", min_similarity=cut) == len(kept)
    assert mnn_score(query, candidate, "similarity", min_similarity=cut) == pytest.approx(
        kept.sum(), abs=1e-5
    )


def test_mnn_score_keeps_a_pair_exactly_at_min_similarity():
    query = torch.tensor([[2.0, 0.0], [0.0, 1.0]])
    candidate = torch.tensor([[1.0, 0.0], [0.0, 3.0]])  # mutual pairs with similarity 2 and 3
    assert mnn_score(query, candidate, min_similarity=2.0) == 2
    assert mnn_score(query, candidate, min_similarity=2.5) == 1
    assert mnn_score(query, candidate, "similarity", min_similarity=2.0) == 5.0


def test_patch_centres_are_row_major_pixel_centres_of_each_patch():
    expected = [[7, 7], [21, 7], [35, 7], [7, 21], [21, 21], [35, 21]]
    np.testing.assert_array_equal(patch_centres(2, 3, 14), expected)


def synthetic_correspondences(seed: int, n_in: int = 60, n_out: int = 60, noise: float = 0.5):
    """``(query_xy, candidate_xy, true_inliers)``: candidate points mapped through a known
    homography (plus noise) for the first ``n_in`` rows, uniform points for the rest;
    the true count is of rows within 3 px of the true mapping."""
    rng = np.random.default_rng(seed)
    homography = np.array([[1.02, 0.04, 15.0], [-0.03, 0.98, -9.0], [2e-4, -1e-4, 1.0]])
    candidate = rng.uniform(0, 320, size=(n_in + n_out, 2))
    mapped = np.c_[candidate, np.ones(len(candidate))] @ homography.T
    exact = mapped[:, :2] / mapped[:, 2:]
    query = exact.copy()
    query[:n_in] += rng.normal(0, noise, size=(n_in, 2))
    query[n_in:] = rng.uniform(0, 320, size=(n_out, 2))
    true_inliers = int((np.linalg.norm(query - exact, axis=1) <= 3.0).sum())
    return query, candidate, true_inliers


@pytest.mark.parametrize("seed", range(3))
def test_ransac_inliers_recover_the_true_inliers_of_a_known_homography(seed):
    pytest.importorskip("cv2")
    query, candidate, true_inliers = synthetic_correspondences(seed)
    assert abs(ransac_inliers(query, candidate, threshold=3.0) - true_inliers) <= 2


def test_ransac_inliers_fit_an_affine_model_too():
    pytest.importorskip("cv2")
    rng = np.random.default_rng(3)
    candidate = rng.uniform(0, 200, size=(50, 2))
    query = candidate @ np.array([[0.9, 0.1], [-0.1, 1.1]]).T + [5.0, -3.0]
    query[35:] = rng.uniform(0, 200, size=(15, 2))
    assert ransac_inliers(query, candidate, threshold=1.0, model="affine") == 35


def test_ransac_inliers_are_the_same_for_the_same_seed_whatever_opencvs_global_rng():
    cv2 = pytest.importorskip("cv2")
    query, candidate, _ = synthetic_correspondences(5, n_in=30, n_out=120, noise=1.0)
    cv2.setRNGSeed(1)
    first = ransac_inliers(query, candidate, threshold=3.0, seed=11, max_iters=50)
    cv2.setRNGSeed(2)
    second = ransac_inliers(query, candidate, threshold=3.0, seed=11, max_iters=50)
    assert first == second


def test_ransac_inliers_draw_different_samples_for_different_seeds():
    pytest.importorskip("cv2")
    # Twenty iterations on a set with 20% inliers: which samples are drawn decides whether
    # the fit finds the homography, so different seeds give different counts if and only
    # if the seed reaches the sampler.
    query, candidate, _ = synthetic_correspondences(2, n_in=30, n_out=120)
    counts = {ransac_inliers(query, candidate, 3.0, seed=s, max_iters=20) for s in range(10)}
    assert len(counts) > 1


@pytest.mark.parametrize("n", range(4))
def test_ransac_inliers_of_fewer_than_four_correspondences_are_zero(n):
    points = np.arange(2 * n, dtype=np.float64).reshape(n, 2)
    assert ransac_inliers(points, points, threshold=1.0) == 0


def test_ransac_inliers_of_collinear_points_are_zero():
    pytest.importorskip("cv2")
    line = np.c_[np.arange(10.0), np.arange(10.0)]
    assert ransac_inliers(line + 1, line, threshold=1.0) == 0


def toy_candidates(seed: int, h: int = 6, w: int = 8, dim: int = 32):
    """Query patches ``[h*w, D]`` and three candidates ``[3, h*w, D]``: unrelated
    features; the query's patches scrambled over the grid; the query's patches shifted
    one patch to the right (the vacated column holds new features)."""
    rng = np.random.default_rng(seed)
    query = unit_rows(rng, h * w, dim)
    grid = query.reshape(h, w, dim)
    unrelated = unit_rows(rng, h * w, dim)
    scrambled = query[rng.permutation(h * w)]
    shifted = np.empty_like(grid)
    shifted[:, 1:] = grid[:, :-1]
    shifted[:, 0] = unit_rows(rng, h, dim)
    return query, np.stack([unrelated, scrambled, shifted.reshape(h * w, dim)])


def test_mnn_ranks_a_candidate_with_the_querys_patches_first_wherever_they_are():
    query, candidates = toy_candidates(0)
    scores = stage_scores(query, candidates, (6, 8), 14, "mnn")
    assert scores.dtype == np.float64 and scores.shape == (3,)
    assert scores[1] == 48  # every patch, scrambled or not, is its own mutual match
    assert scores.argmax() == 1
    assert scores[2] > scores[0]


def test_ransac_ranks_the_shifted_view_of_the_query_above_a_scrambled_one():
    pytest.importorskip("cv2")
    query, candidates = toy_candidates(0)
    scores = stage_scores(query, candidates, (6, 8), 14, "ransac", threshold=0.5)
    assert scores.argmax() == 2
    assert scores[2] == 6 * 7  # the shifted columns fit a translation exactly
    assert scores[1] < 10


def test_min_similarity_drops_weak_pairs_before_counting():
    query, candidates = toy_candidates(1)
    everything = stage_scores(query, candidates, (6, 8), 14, "mnn")
    strong = stage_scores(query, candidates, (6, 8), 14, "mnn", min_similarity=0.99)
    np.testing.assert_array_equal(strong, [0, 48, 42])
    assert (everything >= strong).all()


def test_the_scorer_takes_each_methods_defaults_from_its_entry(monkeypatch):
    # The Reranker entry is the one place of a kind's defaults: changing it
    # changes what the scorer does when the option is left out.
    query, candidates = toy_candidates(0)
    counted = stage_scores(query, candidates, (6, 8), 14, "mnn")
    summed = stage_scores(query, candidates, (6, 8), 14, "mnn", weighting="similarity")
    assert not np.array_equal(counted, summed)
    entry = rerank_module.RERANKERS["mnn"]
    changed = dataclasses.replace(entry, defaults={**entry.defaults, "weighting": "similarity"})
    monkeypatch.setitem(rerank_module.RERANKERS, "mnn", changed)
    np.testing.assert_array_equal(stage_scores(query, candidates, (6, 8), 14, "mnn"), summed)


def test_the_scorer_runs_each_kinds_score_function_with_its_settings():
    pytest.importorskip("cv2")
    query, candidates = toy_candidates(3)
    centres = patch_centres(6, 8, 14)
    for name, reranker in rerank_module.RERANKERS.items():
        settings = {**reranker.defaults, **reranker.fixed}
        pairs = candidate_pairs(torch.as_tensor(query), torch.as_tensor(candidates))
        direct = reranker.scores(pairs, centres, 14, **settings)
        np.testing.assert_array_equal(
            stage_scores(query, candidates, (6, 8), 14, name), direct, err_msg=name
        )


def test_the_scores_of_no_candidates_are_empty():
    query, _ = toy_candidates(2)
    scores = stage_scores(query, np.zeros((0, 48, 32), np.float32), (6, 8), 14, "ransac")
    assert scores.shape == (0,) and scores.dtype == np.float64


def test_rerank_sorts_by_decreasing_score_keeping_retrieval_order_on_ties():
    ranking = np.array([10, 11, 12, 13, 14], dtype=np.int64)
    scores = np.array([1.0, 3.0, 2.0, 3.0, 1.0])
    new_ranking, new_scores = rerank(ranking, scores)
    np.testing.assert_array_equal(new_ranking, [11, 13, 12, 10, 14])
    np.testing.assert_array_equal(new_scores, [3.0, 3.0, 2.0, 1.0, 1.0])
    assert new_ranking.dtype == np.int64 and new_scores.dtype == np.float64


def test_rerank_keeps_missing_candidates_last_whatever_their_score():
    ranking = np.array([10, -1, 11, -1, 12], dtype=np.int64)
    scores = np.array([1.0, 99.0, 3.0, -np.inf, -np.inf])
    new_ranking, new_scores = rerank(ranking, scores)
    np.testing.assert_array_equal(new_ranking, [11, 10, 12, -1, -1])
    np.testing.assert_array_equal(new_scores, [3.0, 1.0, -np.inf, 99.0, -np.inf])


def test_rerank_of_the_top_k_appends_the_rest_of_the_retrieval_in_its_order():
    # K = 3 of D = 6: the head is re-ordered, the tail keeps the retrieval's order and
    # scores as the lowest re-ranked candidate, so scores never rise down the ranking.
    ranking = np.array([10, 11, 12, 13, 14, 15], dtype=np.int64)
    new_ranking, new_scores = rerank(ranking, np.array([1.0, 5.0, 2.0]))
    np.testing.assert_array_equal(new_ranking, [11, 12, 10, 13, 14, 15])
    np.testing.assert_array_equal(new_scores, [5.0, 2.0, 1.0, 1.0, 1.0, 1.0])
    # The retrieval's trailing padding stays last.
    padded = np.array([10, 11, 12, -1, -1], dtype=np.int64)
    new_ranking, _ = rerank(padded, np.array([0.0, 3.0]))
    np.testing.assert_array_equal(new_ranking, [11, 10, 12, -1, -1])


@pytest.mark.parametrize(
    ("call", "named"),
    [
        (lambda: mutual_nearest_neighbours(torch.zeros(4), torch.zeros(3, 4)), "query"),
        (lambda: mutual_nearest_neighbours(torch.zeros(2, 4), torch.zeros(3, 5)), "candidate"),
        (lambda: mutual_nearest_neighbours(torch.zeros(2, 4), torch.zeros(3, 4, 1)), "candidate"),
        (lambda: mnn_score(torch.eye(3), torch.eye(3), "mean"), "weighting"),
        (
            lambda: mnn_score(torch.eye(3), torch.eye(3), min_similarity=float("nan")),
            "min_similarity",
        ),
        (lambda: patch_centres(2, 0, 14), "grid_w"),
        (lambda: patch_centres(2, 3, 0), "patch"),
        (lambda: ransac_inliers(np.zeros((5, 2)), np.zeros((4, 2)), 1.0), "candidate_xy"),
        (lambda: ransac_inliers(np.zeros((5, 3)), np.zeros((5, 3)), 1.0), "query_xy"),
        (lambda: ransac_inliers(np.zeros((5, 2)), np.zeros((5, 2)), 0.0), "threshold"),
        (lambda: ransac_inliers(np.zeros((5, 2)), np.zeros((5, 2)), 1.0, "similarity"), "model"),
        (lambda: ransac_inliers(np.zeros((5, 2)), np.zeros((5, 2)), 1.0, seed=-1), "seed"),
        (lambda: ransac_inliers(np.zeros((5, 2)), np.zeros((5, 2)), 1.0, max_iters=0), "max_iters"),
        (
            lambda: ransac_inliers(np.zeros((5, 2)), np.zeros((5, 2)), 1.0, confidence=1),
            "confidence",
        ),
        (lambda: pair_scorer("sift", {}, (2, 3), 14), "method"),
        (lambda: candidate_pairs(torch.zeros(6, 4), torch.zeros(6, 4)), "candidates"),
        (lambda: candidate_pairs(torch.zeros(6, 4), torch.zeros(2, 6, 4, 1)), "candidates"),
        (lambda: candidate_pairs(torch.zeros(6), torch.zeros(2, 6, 4)), "query"),
        (lambda: candidate_pairs(torch.zeros(6, 4), torch.zeros(2, 6, 5)), "dimension"),
        (lambda: pair_scorer("ransac", {"threshold": -1}, (2, 3), 14), "threshold"),
        (lambda: pair_scorer("mnn", {}, (2, 0), 14), "grid_w"),
        (lambda: rerank(np.array([1, 2]), np.array([1.0, 2.0, 3.0])), "scores"),
        (lambda: rerank(np.array([[1, 2]]), np.array([[1.0, 2.0]])), "ranking_row"),
        (lambda: rerank(np.array([1, -2]), np.array([1.0, 2.0])), "ranking_row"),
        (lambda: rerank(np.array([1, 2]), np.array([1.0, np.nan])), "NaN"),
    ],
)
def test_bad_arguments_raise_value_errors_that_name_them(call, named):
    with pytest.raises(ValueError, match=named):
        call()


def test_the_scorer_rejects_options_of_the_other_method_by_name():
    with pytest.raises(TypeError, match="weighting"):
        pair_scorer("ransac", {"weighting": "count"}, (2, 3), 14)


# ------------------------------------------------------------ batched scores = per-candidate scores


def per_candidate_scores(query, candidates, grid, patch, method, **options):
    """The re-rankers as they were before batching: one float32 product per candidate
    (:func:`mutual_nearest_neighbours`, itself checked against the float64 loop above),
    then the count, the float64 sum of the kept float32 similarities, or the RANSAC fit."""
    settings = rerank_module.reranker(method).settings(options)
    centres = patch_centres(*grid, patch)
    scores = []
    for candidate in candidates:
        i, j, similarity = mutual_nearest_neighbours(query, candidate)
        threshold = settings["min_similarity"]
        kept = np.ones(len(i), bool) if threshold is None else similarity >= threshold
        if method == "ransac":
            fit = {key: settings[key] for key in ("seed", "model", "max_iters", "confidence")}
            pixels = settings["threshold"] * patch
            scores.append(ransac_inliers(centres[i[kept]], centres[j[kept]], pixels, **fit))
        elif settings["weighting"] == "count":
            scores.append(float(kept.sum()))
        else:
            scores.append(float(similarity[kept].astype(np.float64).sum()))
    return np.array(scores, dtype=np.float64)


def hard_candidates(
    seed: int, k: int, h: int = 5, w: int = 6, dim: int = 12, duplicates: bool = True
):
    """A query ``[h*w, D]`` and ``k`` candidates mixing every hard case: near-copies of the
    query (strong pairs), copies nudged by 1e-7 (near-ties within float32 rounding),
    integer rows with duplicates (exact ties), a copy of the query itself and unrelated
    rows; unit rows except the integer ones. ``duplicates``: the query's second half
    repeats its first (ties on the query's side)."""
    rng = np.random.default_rng(seed)
    n = h * w
    query = unit_rows(rng, n, dim)
    if duplicates:  # ties on the query's side too
        query[n // 2 :] = query[: n - n // 2]
    out = []
    for c in range(k):
        kind = c % 5
        if kind == 0:
            out.append(query[rng.permutation(n)] + 0.05 * unit_rows(rng, n, dim))
        elif kind == 1:
            near = query[rng.permutation(n)].copy()
            near[::2] = near[1::2][: len(near[::2])] + 1e-7 * rng.standard_normal((1, dim))
            out.append(near)
        elif kind == 2:
            out.append(integer_rows_with_ties(rng, n, dim))
        elif kind == 3:
            out.append(query.copy())
        else:
            out.append(unit_rows(rng, n, dim))
    return query, np.stack(out).reshape(k, n, dim).astype(np.float32) if out else np.zeros(
        (0, n, dim), np.float32
    )


SETTINGS = [
    ("mnn", {}),
    ("mnn", {"weighting": "similarity"}),
    ("mnn", {"min_similarity": 0.5}),
    ("mnn", {"weighting": "similarity", "min_similarity": 0.9}),
    ("ransac", {"threshold": 0.5}),
    ("ransac", {"min_similarity": 0.5}),
]


@pytest.mark.parametrize(("method", "options"), SETTINGS)
@pytest.mark.parametrize("seed", range(3))
def test_batched_scores_equal_the_per_candidate_scores(method, options, seed):
    if method == "ransac":
        pytest.importorskip("cv2")
    # K = 17 of 30-patch grids: more candidates than patches, ties of every kind.
    query, candidates = hard_candidates(seed, 17)
    expected = per_candidate_scores(query, candidates, (5, 6), 14, method, **options)
    np.testing.assert_array_equal(
        stage_scores(query, candidates, (5, 6), 14, method, **options), expected
    )


@pytest.mark.parametrize("k", [0, 1, 3])
@pytest.mark.parametrize("method", ["mnn", "ransac"])
def test_batched_scores_of_zero_one_and_few_candidates(method, k):
    if method == "ransac":
        pytest.importorskip("cv2")
    query, candidates = hard_candidates(4, k)
    scores = stage_scores(query, candidates, (5, 6), 14, method)
    assert scores.shape == (k,) and scores.dtype == np.float64
    np.testing.assert_array_equal(
        scores, per_candidate_scores(query, candidates, (5, 6), 14, method)
    )


def test_candidate_pairs_equal_the_float64_double_loop_with_ties():
    # Not the 1e-7 nudges (kind 1): float32 and float64 may order those either way.
    query, candidates = hard_candidates(5, 10)
    candidates = candidates[[c for c in range(10) if c % 5 != 1]]
    for candidate, (i, j, similarity) in zip(
        candidates, candidate_pairs(query, candidates), strict=True
    ):
        expected = direct_mnn(query, candidate)
        assert list(zip(i.tolist(), j.tolist(), strict=True)) == [(a, b) for a, b, _ in expected]
        np.testing.assert_allclose(similarity, [v for _, _, v in expected], rtol=0, atol=1e-6)
        assert i.dtype == j.dtype == np.int64


# ------------------------------------------------------------ pairs once, scored by each re-ranker


@pytest.mark.parametrize("seed", range(3))
def test_candidate_pairs_are_each_candidates_mutual_nearest_neighbours(seed):
    """What the matches stage stores: every candidate's pairs and float32 similarities
    exactly as the per-candidate product gives them (ties, near-ties, copies), with no
    threshold applied."""
    query, candidates = hard_candidates(seed, 17)
    pairs = candidate_pairs(query, candidates)
    assert len(pairs) == len(candidates)
    for candidate, (i, j, similarity) in zip(candidates, pairs, strict=True):
        expected = mutual_nearest_neighbours(query, candidate)
        for got, want in zip((i, j, similarity), expected, strict=True):
            assert got.dtype == want.dtype
            np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("per_product", [None, 2, 1])
@pytest.mark.parametrize("seed", range(3))
def test_pairs_read_on_the_device_are_the_per_candidate_pairs_bit_for_bit(
    monkeypatch, seed, per_product
):
    """The path other devices take (the batched product's argmax and similarities read by
    torch where the product is), run on the CPU: every candidate's pairs and float32
    similarities those of its own product (exact ties on both sides, duplicate patches,
    near-ties within rounding, a NaN), whether a product holds all 17 candidates, two or
    one."""
    monkeypatch.setattr(rerank_module, "_host_argmax", lambda device: False)
    if per_product is not None:
        monkeypatch.setattr(rerank_module, "_DEVICE_PRODUCT_ELEMENTS", per_product * 30 * 30)
    query, candidates = hard_candidates(seed, 17)
    candidates[6, 4, 2] = np.nan
    pairs = candidate_pairs(torch.from_numpy(query), candidates)
    assert len(pairs) == len(candidates)
    for candidate, found in zip(candidates, pairs, strict=True):
        for got, want in zip(found, mutual_nearest_neighbours(query, candidate), strict=True):
            assert got.dtype == want.dtype
            np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize(("method", "options"), SETTINGS)
@pytest.mark.parametrize("seed", range(3))
def test_scores_from_stored_pairs_equal_the_scores_from_features(method, options, seed):
    """The pair scorers over candidate_pairs (as the matches store holds them: int32
    patch indices) give the per-candidate scores bit for bit, whatever min_similarity
    keeps (ties and a threshold on a pair's value included)."""
    if method == "ransac":
        pytest.importorskip("cv2")
    query, candidates = hard_candidates(seed, 17)
    settings = rerank_module.reranker(method).settings(options)
    centres = patch_centres(5, 6, 14)
    pairs = candidate_pairs(query, candidates)
    if "min_similarity" in options:  # a pair exactly at the threshold is kept
        exact = next(s for _, _, s in pairs if len(s))
        settings["min_similarity"] = float(exact[0])
    stored = [(i.astype(np.int32), j.astype(np.int32), s.copy()) for i, j, s in pairs]
    scorer = {"mnn": mnn_pair_scores, "ransac": ransac_pair_scores}[method]
    expected = per_candidate_scores(query, candidates, (5, 6), 14, method, **settings)
    np.testing.assert_array_equal(scorer(stored, centres, 14, **settings), expected)
    np.testing.assert_array_equal(scorer(pairs, centres, 14, **settings), expected)
    options = {k: v for k, v in settings.items() if k in rerank_module.reranker(method).options}
    np.testing.assert_array_equal(
        stage_scores(query, candidates, (5, 6), 14, method, **options), expected
    )


def test_a_similarity_sum_from_pairs_adds_the_float32_values_in_query_patch_order():
    # float64 sums of values that cancel differently in another order: the pairs' order
    # (increasing query patch) is mnn_score's.
    values = np.array([1e8, 1.0, -1e8, 1.0], dtype=np.float32)
    pairs = [(np.arange(4), np.arange(4), values)]
    (score,) = mnn_pair_scores(pairs, None, 14, weighting="similarity", min_similarity=None)
    assert score == float(values.astype(np.float64).sum())
    (count,) = mnn_pair_scores(pairs, None, 14, weighting="count", min_similarity=1.0)
    assert count == 3


def test_pair_scorers_refuse_bad_pairs_and_options_by_name():
    with pytest.raises(ValueError, match=r"pairs\[0\] must be .*float32"):
        mnn_pair_scores(
            [(np.arange(2), np.arange(2), np.ones(2))], None, 14, weighting="count",
            min_similarity=None,
        )  # fmt: skip
    with pytest.raises(ValueError, match="weighting"):
        mnn_pair_scores([], None, 14, weighting="sum", min_similarity=None)
    with pytest.raises(ValueError, match="threshold"):
        ransac_pair_scores(
            [], None, 14, min_similarity=None, threshold=0, seed=0, model="homography",
            max_iters=10, confidence=0.9,
        )  # fmt: skip


@pytest.mark.parametrize("threads", [1, 2, 3])
@pytest.mark.parametrize("n_k", [1, 4, 9])
def test_direct_pairs_by_blocks_on_threads_are_the_whole_arrays_argmax(threads, n_k):
    # Ties (values rounded to a grid), NaN (the maximum, first index first) and -inf.
    rng = np.random.default_rng(n_k * 10 + threads)
    similarity = np.round(rng.standard_normal((13, n_k, 11)), 1).astype(np.float32)
    similarity[rng.random(similarity.shape) < 0.03] = np.nan
    similarity[rng.random(similarity.shape) < 0.03] = -np.inf
    forward, mutual, values = rerank_module._direct_pairs(similarity, threads)
    # Direct: a double loop per candidate, each argmax the first maximal index (NaN first).
    for k in range(n_k):
        block = similarity[:, k, :].astype(np.float64)
        for i in range(13):
            row = block[i]
            j = (
                int(np.flatnonzero(np.isnan(row))[0])
                if np.isnan(row).any()
                else int(np.flatnonzero(row == row.max())[0])
            )
            column = block[:, j]
            back = (
                int(np.flatnonzero(np.isnan(column))[0])
                if np.isnan(column).any()
                else int(np.flatnonzero(column == column.max())[0])
            )
            assert forward[k, i] == j
            assert mutual[k, i] == (back == i)
            assert np.array_equal(values[k, i], np.float32(block[i, j]), equal_nan=True)


def test_the_batched_product_is_the_per_candidate_product_bit_for_bit():
    # What makes the batched scores the per-candidate ones: the BLAS computes each element
    # of the [P, K * Q] product as it does in a [P, Q] one.
    rng = np.random.default_rng(6)
    for patches, dim in ((30, 12), (300, 104), (256, 768)):
        query = torch.from_numpy(unit_rows(rng, patches, dim))
        candidates = torch.from_numpy(unit_rows(rng, 7 * patches, dim)).view(7, patches, dim)
        # The product candidate_pairs takes.
        batched = (query @ candidates.reshape(-1, dim).T).view(patches, 7, patches)
        for c in range(7):
            assert torch.equal(batched[:, c], query @ candidates[c].T)


@pytest.mark.parametrize("method", ["mnn", "ransac"])
def test_scores_are_the_same_over_several_products(monkeypatch, method):
    if method == "ransac":
        pytest.importorskip("cv2")
    query, candidates = hard_candidates(7, 11)
    whole = stage_scores(query, candidates, (5, 6), 14, method)
    # Two candidates a product: six products, the last with one candidate.
    monkeypatch.setattr(rerank_module, "_PRODUCT_ELEMENTS", 2 * 30 * 30)
    np.testing.assert_array_equal(stage_scores(query, candidates, (5, 6), 14, method), whole)


def test_non_finite_descriptors_score_as_the_per_candidate_path():
    query, candidates = hard_candidates(10, 4)
    candidates[2, 3, 0] = np.nan
    np.testing.assert_array_equal(
        stage_scores(query, candidates, (5, 6), 14, "mnn"),
        per_candidate_scores(query, candidates, (5, 6), 14, "mnn"),
    )


# ------------------------------------------------------------ a re-ranker shallower than the table


def test_a_reranked_rows_recall_beyond_its_top_k_is_its_retrievals(tmp_path):
    """anyloc_vlad re-ranked by mnn over its top 2 of 6 references, the table reading
    Recall@1, 2, 4 and 6: the re-ranked ranking is as deep as the retrieval's, its top 2
    the retrieval's top 2 re-ordered and the rest the retrieval's in order, so Recall@N
    for N >= 2 is the retrieval's. The truth (query q's positive is reference q + 3)
    makes the retrieval's Recall@4 exceed its Recall@2, which a ranking truncated at the
    re-ranker's 2 would have reported for Recall@4 too."""
    root = make_dataset(tmp_path / "data" / "toy", n_places=6, width=64, height=48)
    rows = np.empty((6, 2), dtype=object)
    for q in range(6):
        rows[q] = q, [(q + 3) % 6]
    np.save(root / "ground_truth_new.npy", rows, allow_pickle=True)
    config = toy_config(
        tmp_path / "data",
        resolution=[64, 48],
        recall_at=[1, 2, 4, 6],
        methods=["anyloc_vlad"],
        rerank={"anyloc_vlad": ["mnn"]},
    )
    config["rerankers"] = {"mnn": {"kind": "mnn", "features": "daisy", "top_k": 2}}
    plan = build_plan(validate_config(config, SCHEMA))
    done: dict = {}
    runs = {run.method: run for run in plan.runs["toy"]}
    retrieval, reranked = (
        stores.open_store(
            run_stage(
                plan, "recall", runs[m].recall_key, tmp_path / "data", tmp_path / "cache", done
            )
        )
        for m in ("anyloc_vlad", "anyloc_vlad+mnn")
    )
    before = np.asarray(retrieval["ranking"][...])
    after = np.asarray(reranked["ranking"][...])
    assert after.shape == before.shape == (6, 6)
    np.testing.assert_array_equal(np.sort(after[:, :2], axis=1), np.sort(before[:, :2], axis=1))
    np.testing.assert_array_equal(after[:, 2:], before[:, 2:])
    # The stored score kind is the Reranker entry's (what the table and figures read).
    assert reranked.attrs["score"] == rerank_module.RERANKERS["mnn"].score
    recall, recall_reranked = retrieval.attrs["recall"], reranked.attrs["recall"]
    assert recall["4"] > recall["2"]  # the case is one a truncated ranking would get wrong
    for n in ("2", "4", "6"):
        assert recall_reranked[n] == recall[n]
    assert recall_reranked["6"] == 1.0


def test_a_reranker_deeper_than_the_references_reorders_them_all(tmp_path):
    """top_k 10 over 6 references: every retrieved reference is re-ranked (the stage caps
    K at the retrieval's depth) and the row is a permutation of the retrieval's."""
    make_dataset(tmp_path / "data" / "toy", n_places=6, width=64, height=48)
    config = toy_config(
        tmp_path / "data", resolution=[64, 48], recall_at=[1, 6], methods=["anyloc_vlad"],
        rerank={"anyloc_vlad": ["mnn"]},
    )  # fmt: skip
    config["rerankers"] = {"mnn": {"kind": "mnn", "features": "daisy", "top_k": 10}}
    plan = build_plan(validate_config(config, SCHEMA))
    done: dict = {}
    runs = {run.method: run for run in plan.runs["toy"]}
    before, after = (
        np.asarray(
            stores.open_store(
                run_stage(
                    plan, "recall", runs[m].recall_key, tmp_path / "data", tmp_path / "cache", done
                )
            )["ranking"][...]
        )
        for m in ("anyloc_vlad", "anyloc_vlad+mnn")
    )
    assert after.shape == before.shape == (6, 6)
    np.testing.assert_array_equal(np.sort(after, axis=1), np.sort(before, axis=1))
