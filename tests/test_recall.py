"""Recall@N (REFERENCE.md section 2 step 9) against a direct loop. Results are exact
fractions, compared with a 1e-12 absolute tolerance."""

from __future__ import annotations

import numpy as np
import pytest

from vprflow.recall import correct_at, recall_at


def direct_recall(ranking, truth, ns):
    out = {}
    for n in ns:
        evaluated = hits = 0
        for row, positives in zip(ranking, truth, strict=True):
            if len(positives) == 0:
                continue
            evaluated += 1
            if any(int(r) in {int(p) for p in positives} for r in list(row)[:n]):
                hits += 1
        out[n] = hits / evaluated
    return out


def direct_first(ranking, truth):
    out = []
    for row, positives in zip(ranking, truth, strict=True):
        rank = -1
        for position, r in enumerate(row):
            if r in set(positives.tolist()):
                rank = position
                break
        out.append(rank)
    return out


def random_problem(seed, n_query=40, n_ref=30, top=10):
    rng = np.random.default_rng(seed)
    ranking = np.stack([rng.permutation(n_ref)[:top] for _ in range(n_query)])
    truth = []
    for q in range(n_query):
        size = rng.integers(0, 4)  # some queries have no positive
        truth.append(np.sort(rng.choice(n_ref, size, replace=False)).astype(np.int64))
        if q % 5 == 0:
            truth[q] = np.zeros(0, dtype=np.int64)
    return ranking, truth


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4])
def test_recall_at_matches_direct_loop(seed):
    ranking, truth = random_problem(seed)
    ns = [1, 2, 5, 10, 20]
    out = recall_at(ranking, truth, ns)
    expected = direct_recall(ranking, truth, ns)
    assert list(out) == ns
    for n in ns:
        assert out[n] == pytest.approx(expected[n], abs=1e-12)
    values = [out[n] for n in ns]
    assert values == sorted(values)  # recall never decreases with N


def test_queries_without_positives_are_excluded():
    ranking = np.array([[0, 1], [1, 0], [0, 1]])
    truth = [np.array([0]), np.array([], dtype=np.int64), np.array([1])]
    # Counting the positive-less query as a miss would give 1/3 at N = 1.
    assert recall_at(ranking, truth, [1, 2]) == {1: 0.5, 2: 1.0}


def test_recall_needs_a_query_with_positives():
    ranking = np.array([[0, 1], [1, 0]])
    with pytest.raises(ValueError, match="no query has a ground-truth positive"):
        recall_at(ranking, [np.zeros(0, np.int64)] * 2, [1])


def test_recall_needs_one_truth_per_query():
    with pytest.raises(ValueError):
        recall_at(np.array([[0, 1], [1, 0]]), [np.array([0])], [1])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_correct_at_is_rank_of_first_positive(seed):
    ranking, truth = random_problem(seed)
    out = correct_at(ranking, truth)
    assert out.dtype == np.int64
    np.testing.assert_array_equal(out, direct_first(ranking, truth))
    assert (out[[len(t) == 0 for t in truth]] == -1).all()


def test_correct_at_small_example():
    ranking = np.array([[4, 2, 7], [1, 3, 5], [9, 8, 6]])
    truth = [np.array([7, 2]), np.array([0]), np.array([9])]
    np.testing.assert_array_equal(correct_at(ranking, truth), [1, -1, 0])
