"""vprflow.evaluation.precision_recall against slow, by-hand versions of VPR-Bench's definitions
(performance_comparison.py at MubarizZaffar/VPR-Bench 77ad30f3: sklearn's
precision_recall_curve of "top-1 is a positive" labels, sklearn's auc, and EP)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vprflow.evaluation.precision_recall import (
    auc_pr,
    extended_precision,
    precision_recall_curve,
    recall_at_100_precision,
    summary,
    top1_confidence,
)

# float64 sums of at most a few hundred terms: far below this.
TOLERANCE = 1e-12
SEEDS = range(12)


def slow_curve(confidence, correct):
    """One point per distinct finite confidence, highest first, counted query by query:
    TP accepted and correct, FP accepted and wrong (no positive or not), FN rejected and
    correct. -inf is never accepted."""
    thresholds = sorted({float(c) for c in confidence if c > -math.inf}, reverse=True)
    precision, recall = [], []
    for t in thresholds:
        tp = fp = fn = 0
        for c, ok in zip(confidence, correct, strict=True):
            accepted = c >= t
            if accepted and ok:
                tp += 1
            elif accepted:
                fp += 1
            elif ok:
                fn += 1
        precision.append(tp / (tp + fp))
        recall.append(tp / (tp + fn))
    return precision, recall, thresholds


def slow_auc(precision, recall):
    """Trapezoids from sklearn's extra point (recall 0, precision 1) through the curve."""
    points = [(0.0, 1.0), *zip(recall, precision, strict=True)]
    area = 0.0
    for (r0, p0), (r1, p1) in zip(points, points[1:], strict=False):
        area += (r1 - r0) * (p0 + p1) / 2
    return area


def slow_recall_at_full_precision(precision, recall):
    return max([r for p, r in zip(precision, recall, strict=True) if p == 1.0], default=0.0)


def slow_extended_precision(precision, recall):
    first = precision[0]
    full = slow_recall_at_full_precision(precision, recall) if first == 1.0 else 0.0
    return (first + full) / 2


def random_queries(seed):
    """Confidences from a few values (many ties), some -inf, a quarter of the queries
    without a positive, and at least one correct top-1."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 60))
    confidence = rng.integers(0, 8, n) / 4 - 1
    confidence[rng.random(n) < 0.1] = -np.inf
    has_positive = rng.random(n) < 0.75
    correct = has_positive & (rng.random(n) < 0.6)
    has_positive[0] = correct[0] = True
    return confidence, correct, has_positive


@pytest.mark.parametrize("seed", SEEDS)
def test_the_curve_counts_tp_fp_fn_at_every_distinct_confidence_like_the_slow_loop(seed):
    confidence, correct, has_positive = random_queries(seed)
    precision, recall, thresholds = precision_recall_curve(confidence, correct, has_positive)
    slow_p, slow_r, slow_t = slow_curve(confidence.tolist(), correct.tolist())
    assert precision.dtype == recall.dtype == thresholds.dtype == np.float64
    np.testing.assert_array_equal(thresholds, slow_t)
    np.testing.assert_allclose(precision, slow_p, rtol=0, atol=TOLERANCE)
    np.testing.assert_allclose(recall, slow_r, rtol=0, atol=TOLERANCE)


@pytest.mark.parametrize("seed", SEEDS)
def test_the_summary_numbers_match_the_slow_formulas(seed):
    confidence, correct, has_positive = random_queries(seed)
    slow_p, slow_r, _ = slow_curve(confidence.tolist(), correct.tolist())
    precision, recall, _ = precision_recall_curve(confidence, correct, has_positive)
    assert abs(auc_pr(precision, recall) - slow_auc(slow_p, slow_r)) <= TOLERANCE
    assert (
        abs(
            recall_at_100_precision(precision, recall)
            - slow_recall_at_full_precision(slow_p, slow_r)
        )
        <= TOLERANCE
    )
    assert (
        abs(extended_precision(precision, recall) - slow_extended_precision(slow_p, slow_r))
        <= TOLERANCE
    )
    result = summary(confidence, correct, has_positive)
    assert result == {
        "auc_pr": auc_pr(precision, recall),
        "recall_at_100_precision": recall_at_100_precision(precision, recall),
        "extended_precision": extended_precision(precision, recall),
    }
    assert all(type(value) is float for value in result.values())


@pytest.mark.parametrize("seed", SEEDS)
def test_permuting_the_queries_changes_nothing(seed):
    confidence, correct, has_positive = random_queries(seed)
    order = np.random.default_rng(seed + 100).permutation(len(confidence))
    before = precision_recall_curve(confidence, correct, has_positive)
    after = precision_recall_curve(confidence[order], correct[order], has_positive[order])
    for a, b in zip(before, after, strict=True):
        np.testing.assert_array_equal(a, b)
    assert summary(confidence, correct, has_positive) == summary(
        confidence[order], correct[order], has_positive[order]
    )


def test_a_hand_worked_curve_with_a_tie_and_a_query_without_positive():
    # 0.9 right | 0.8 right, 0.8 wrong (tie) | 0.5 right | 0.3 no positive.
    confidence = np.array([0.8, 0.3, 0.9, 0.5, 0.8])
    correct = np.array([False, False, True, True, True])
    has_positive = np.array([True, False, True, True, True])
    precision, recall, thresholds = precision_recall_curve(confidence, correct, has_positive)
    np.testing.assert_array_equal(thresholds, [0.9, 0.8, 0.5, 0.3])
    np.testing.assert_allclose(precision, [1, 2 / 3, 3 / 4, 3 / 5], rtol=0, atol=TOLERANCE)
    np.testing.assert_allclose(recall, [1 / 3, 2 / 3, 1, 1], rtol=0, atol=TOLERANCE)
    # (0,1)-(1/3,1): 1/3; -(2/3,2/3): 5/18; -(1,3/4): 17/72; -(1,3/5): 0.
    assert abs(auc_pr(precision, recall) - 61 / 72) <= TOLERANCE
    assert recall_at_100_precision(precision, recall) == pytest.approx(1 / 3, abs=TOLERANCE)
    assert extended_precision(precision, recall) == pytest.approx(2 / 3, abs=TOLERANCE)


def test_a_wrong_most_confident_match_gives_zero_extended_precision():
    precision, recall, _ = precision_recall_curve(
        np.array([0.9, 0.5]), np.array([False, True]), np.array([True, True])
    )
    np.testing.assert_array_equal(precision, [0.0, 0.5])
    np.testing.assert_array_equal(recall, [0.0, 1.0])
    assert auc_pr(precision, recall) == pytest.approx(0.25, abs=TOLERANCE)
    assert recall_at_100_precision(precision, recall) == 0.0
    assert extended_precision(precision, recall) == 0.0


def test_a_correct_query_with_no_match_stays_a_false_negative():
    precision, recall, thresholds = precision_recall_curve(
        np.array([1.0, -np.inf]), np.array([True, True]), np.array([True, True])
    )
    np.testing.assert_array_equal(thresholds, [1.0])
    np.testing.assert_array_equal(precision, [1.0])
    np.testing.assert_array_equal(recall, [0.5])
    assert auc_pr(precision, recall) == 0.5
    assert extended_precision(precision, recall) == 0.75


def test_extended_precision_is_the_mean_of_precision_at_first_recall_and_recall_at_full_precision():
    for seed in SEEDS:
        precision, recall, _ = precision_recall_curve(*random_queries(seed))
        expected = (precision[0] + recall_at_100_precision(precision, recall)) / 2
        assert extended_precision(precision, recall) == pytest.approx(expected, abs=TOLERANCE)


def test_extended_precision_ignores_full_precision_when_the_first_point_is_imperfect():
    # Not a curve precision_recall_curve can give; VPR-Bench's guard still applies.
    precision, recall = np.array([0.5, 1.0]), np.array([0.2, 0.4])
    assert recall_at_100_precision(precision, recall) == 0.4
    assert extended_precision(precision, recall) == 0.25


def test_a_query_without_positive_counts_as_a_wrong_match():
    confidence = np.array([0.7, 0.6, 0.2, 0.1])
    correct = np.array([True, False, True, False])
    with_positive = precision_recall_curve(confidence, correct, np.ones(4, dtype=bool))
    without = precision_recall_curve(confidence, correct, np.array([True, False, True, False]))
    for a, b in zip(with_positive, without, strict=True):
        np.testing.assert_array_equal(a, b)


def test_equal_confidences_are_one_threshold():
    precision, recall, thresholds = precision_recall_curve(
        np.array([0.0, -0.0, 0.0]), np.array([True, False, True]), np.ones(3, dtype=bool)
    )
    np.testing.assert_array_equal(thresholds, [0.0])
    assert not np.signbit(thresholds[0])
    np.testing.assert_allclose(precision, [2 / 3], rtol=0, atol=TOLERANCE)
    np.testing.assert_array_equal(recall, [1.0])


def test_top1_confidence_negates_distances_and_keeps_votes_and_similarities():
    scores = np.array([[0.5, 0.7], [2.0, 3.0]], dtype=np.float32)
    np.testing.assert_array_equal(top1_confidence(scores, "squared_l2"), [-0.5, -2.0])
    np.testing.assert_array_equal(top1_confidence(scores, "votes"), [0.5, 2.0])
    np.testing.assert_array_equal(top1_confidence(scores, "similarity"), [0.5, 2.0])
    assert top1_confidence(scores, "votes").dtype == np.float64


def test_top1_confidence_is_minus_infinity_for_a_query_without_a_usable_match():
    scores = np.array([[np.nan, 1.0], [np.inf, 1.0], [-np.inf, 1.0], [3.4e38, 4.0], [1.0, 2.0]])
    ranking = np.array([[0, 1], [0, 1], [0, 1], [-1, -1], [2, 0]])
    expected = [-np.inf, -np.inf, -np.inf, -np.inf, -1.0]
    np.testing.assert_array_equal(top1_confidence(scores, "squared_l2", ranking), expected)
    np.testing.assert_array_equal(
        top1_confidence(np.zeros((3, 0)), "votes"), [-np.inf, -np.inf, -np.inf]
    )


def test_top1_confidence_rejects_an_unknown_kind_and_bad_shapes():
    with pytest.raises(ValueError, match="'cosine'"):
        top1_confidence(np.zeros((2, 2)), "cosine")
    with pytest.raises(ValueError, match="scores"):
        top1_confidence(np.zeros(2), "votes")
    with pytest.raises(ValueError, match="ranking"):
        top1_confidence(np.zeros((2, 2)), "votes", np.zeros((3, 2), dtype=int))


@pytest.mark.parametrize(
    ("confidence", "correct", "has_positive", "message"),
    [
        ([0.1, 0.2], [True], [True, True], "correct has 1 entries"),
        ([0.1, 0.2], [True, False], [True], "has_positive has 1 entries"),
        ([[0.1, 0.2]], [True, False], [True, True], "confidence must be 1-D"),
        ([], [], [], "confidence is empty"),
        ([0.1, np.nan], [True, False], [True, True], "confidence has 1 NaN"),
        ([0.1, np.inf], [True, False], [True, True], r"confidence has \+inf"),
        ([0.1, 0.2], [1, 0], [True, True], "correct must be boolean"),
        ([0.1, 0.2], [False, False], [False, False], "has_positive: no query"),
        ([0.1, 0.2], [True, False], [False, True], r"correct: queries \[0\]"),
        ([0.1, 0.2], [False, False], [True, True], "correct: no top-1"),
        ([-np.inf, -np.inf], [True, False], [True, True], "confidence: every query"),
    ],
)
def test_the_curve_rejects_bad_input_naming_the_argument(
    confidence, correct, has_positive, message
):
    with pytest.raises(ValueError, match=message):
        precision_recall_curve(np.array(confidence), np.array(correct), np.array(has_positive))


@pytest.mark.parametrize("function", [auc_pr, recall_at_100_precision, extended_precision])
@pytest.mark.parametrize(
    ("precision", "recall", "message"),
    [
        ([1.0, 0.5], [0.5], "precision has 2 points but recall has 1"),
        ([], [], "precision is empty"),
        ([np.nan], [0.5], "precision has NaN"),
        ([1.0], [1.5], r"recall has value\(s\) outside"),
        ([1.0, 1.0], [0.5, 0.2], "recall must be non-decreasing"),
        ([[1.0]], [[0.5]], "precision must be 1-D"),
    ],
)
def test_the_curve_metrics_reject_bad_curves_naming_the_argument(
    function, precision, recall, message
):
    with pytest.raises(ValueError, match=message):
        function(np.array(precision), np.array(recall))
