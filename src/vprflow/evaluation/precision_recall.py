"""Precision-recall of top-1 place matches, as VPR-Bench defines it.

Source read: MubarizZaffar/VPR-Bench, ``performance_comparison.py`` at commit
``77ad30f3684476717188c67d7f3f66be19f832af`` (HEAD; the file last changed in
``c5bff34ae59fbd43858f5a263743ee194edf976f``). Written from that reading, not copied:

* lines 252-261 (``compute_matches``): a query's label is 1 when its retrieved
  (top-1) reference is in its ground-truth list, else 0. A query with no positive
  has an empty list, so its label is 0, exactly like a query whose top-1 is wrong.
* lines 22-24 (``compute_precision_recall``): ``sklearn.metrics.precision_recall_curve``
  of those labels against the top-1 matching scores (the best similarity, higher is
  more confident). sklearn puts one point at every distinct score, accepts the
  queries whose score is ``>=`` that threshold, and gives
  precision = TP / (TP + FP) and recall = TP / (number of label-1 queries); it then
  appends a point (recall 0, precision 1) that has no threshold.
* lines 37-38 (``compute_auc_PR``): ``sklearn.metrics.auc(recall, precision)``, the
  trapezoidal rule over the curve, that appended (0, 1) point included.
* lines 105-114 (``compute_extendedprecision``): P_R0 is ``precision[-2]``, the precision
  at the highest threshold (the lowest recall; ``[-1]`` is the appended point);
  R_P100 is the recall of the lowest threshold whose precision is 1, and is 0 when
  P_R0 < 1; EP = (P_R0 + R_P100) / 2.

So, at a threshold ``t`` (a query's match is accepted when its confidence >= ``t``):

* TP: an accepted query whose top-1 is correct.
* FP: an accepted query whose top-1 is wrong, whether or not the database holds a
  positive for it; a query with no positive can only be an FP or a TN.
* FN: a rejected query whose top-1 is correct. A rejected wrong match is a TN, not an
  FN, even when a positive exists: recall's denominator is the number of correct top-1
  matches, not the number of queries with a positive, so recall reaches 1 at the
  lowest threshold.

``has_positive`` therefore changes no count; it is checked for consistency only.

Two cases VPR-Bench never meets, decided here:

* A query with confidence ``-inf`` (it ranks nothing, or its score is not finite) is
  never accepted and sets no threshold: a correct one stays an FN at every threshold,
  as a never-retrieved item does in VLFeat's ``vl_pr``, so recall may stay below 1.
* sklearn (0.20 and earlier, what VPR-Bench's Python 2 environment gets) drops the
  points below the first threshold that reaches full recall; they are kept here. They
  all have recall 1, so they add no area and change neither R_P100 nor P_R0.
"""

from __future__ import annotations

import numpy as np

# How the recall stage's scores read: squared L2 distances of global descriptors (lower is
# better); SegVLAD's votes, similarities and a re-ranker's local matches (higher is better).
SCORE_KINDS = ("squared_l2", "votes", "similarity", "matches")


def top1_confidence(scores: np.ndarray, kind: str, ranking: np.ndarray | None = None) -> np.ndarray:
    """Confidence of each query's top-1 match, higher is more confident: float64 ``[Nq]``.

    ``scores`` ``[Nq, k]`` as the recall stage stores them, best first. ``kind``
    ``"squared_l2"`` (lower is better) is negated; ``"votes"``, ``"similarity"`` and
    ``"matches"`` (higher is better) are kept. A query gets ``-inf`` (never accepted) when it ranks
    nothing (``k == 0``, or ``ranking`` ``[Nq, k]`` given and its first index is
    negative) or when its first score is NaN or infinite.
    """
    if kind not in SCORE_KINDS:
        raise ValueError(f"unknown score kind {kind!r}; expected one of {SCORE_KINDS}")
    scores = np.asarray(scores, dtype=np.float64)
    if scores.ndim != 2:
        raise ValueError(f"scores must be 2-D [Nq, k], got shape {scores.shape}")
    confidence = np.full(len(scores), -np.inf)
    if scores.shape[1] == 0:
        return confidence
    first = scores[:, 0]
    valid = np.isfinite(first)
    if ranking is not None:
        ranking = np.asarray(ranking)
        if ranking.ndim != 2 or len(ranking) != len(scores) or ranking.shape[1] < 1:
            raise ValueError(
                f"ranking must be [Nq, k>=1] with Nq = {len(scores)}, got shape {ranking.shape}"
            )
        # faiss pads a short row with index -1 and a huge, finite distance: the index
        # is the only reliable sign that there is no match.
        valid &= ranking[:, 0] >= 0
    confidence[valid] = -first[valid] if kind == "squared_l2" else first[valid]
    return confidence


def _query_vector(values: np.ndarray, name: str) -> np.ndarray:
    values = np.asarray(values)
    if values.ndim != 1:
        raise ValueError(f"{name} must be 1-D [Nq], got shape {values.shape}")
    if len(values) == 0:
        raise ValueError(f"{name} is empty: there are no queries")
    return values


def _flags(values: np.ndarray, name: str, n: int) -> np.ndarray:
    values = _query_vector(values, name)
    if values.dtype != bool:
        raise ValueError(f"{name} must be boolean, got dtype {values.dtype}")
    if len(values) != n:
        raise ValueError(f"{name} has {len(values)} entries but confidence has {n}")
    return values


def precision_recall_curve(
    confidence: np.ndarray, correct: np.ndarray, has_positive: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """VPR-Bench's precision-recall curve of top-1 matches (definitions: module docstring).

    ``confidence`` float ``[Nq]`` (higher is more confident; ``-inf`` means no match),
    ``correct`` bool ``[Nq]`` (the top-1 is a positive), ``has_positive`` bool ``[Nq]``.
    Returns float64 ``(precision [T], recall [T], thresholds [T])``, one point per
    distinct finite confidence, by decreasing threshold (so recall is non-decreasing).
    """
    confidence = _query_vector(confidence, "confidence").astype(np.float64)
    n = len(confidence)
    correct = _flags(correct, "correct", n)
    has_positive = _flags(has_positive, "has_positive", n)
    if np.isnan(confidence).any():
        raise ValueError(f"confidence has {int(np.isnan(confidence).sum())} NaN value(s)")
    if (confidence == np.inf).any():
        raise ValueError("confidence has +inf value(s); only finite values and -inf are allowed")
    if not has_positive.any():
        raise ValueError("has_positive: no query has a positive in the database")
    if (correct & ~has_positive).any():
        bad = np.flatnonzero(correct & ~has_positive)[:5].tolist()
        raise ValueError(f"correct: queries {bad} are correct but have no positive")
    n_correct = int(correct.sum())
    if n_correct == 0:
        # VPR-Bench's recall would be 0/0 here (sklearn returns NaN).
        raise ValueError(
            "correct: no top-1 match is correct, so recall (TP / correct) is undefined"
        )
    accepted = confidence > -np.inf
    if not accepted.any():
        raise ValueError("confidence: every query is -inf (no match), so the curve is empty")
    # Adding 0.0 turns -0.0 into 0.0, so a tie of the two zeros reports one threshold value.
    values = confidence[accepted] + 0.0
    ascending, group = np.unique(values, return_inverse=True)
    n_groups = len(ascending)
    per_group = np.bincount(group, minlength=n_groups)[::-1]
    correct_per_group = np.bincount(group[correct[accepted]], minlength=n_groups)[::-1]
    # Counting whole groups of equal confidence makes a tie one threshold, whatever the
    # order of the queries.
    n_accepted = np.cumsum(per_group)
    tp = np.cumsum(correct_per_group)
    precision = tp / n_accepted
    recall = tp / n_correct
    return precision, recall, ascending[::-1].copy()


def _curve(precision: np.ndarray, recall: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    precision = np.asarray(precision, dtype=np.float64)
    recall = np.asarray(recall, dtype=np.float64)
    for name, values in (("precision", precision), ("recall", recall)):
        if values.ndim != 1:
            raise ValueError(f"{name} must be 1-D [T], got shape {values.shape}")
        if len(values) == 0:
            raise ValueError(f"{name} is empty: the curve has no point")
        if not np.isfinite(values).all():
            raise ValueError(f"{name} has NaN or infinite value(s)")
        if (values < 0).any() or (values > 1).any():
            raise ValueError(f"{name} has value(s) outside [0, 1]")
    if precision.shape != recall.shape:
        raise ValueError(
            f"precision has {len(precision)} points but recall has {len(recall)}; "
            "they must come from the same curve"
        )
    if (np.diff(recall) < 0).any():
        raise ValueError("recall must be non-decreasing (points by decreasing threshold)")
    return precision, recall


def auc_pr(precision: np.ndarray, recall: np.ndarray) -> float:
    """Area under the precision-recall curve, VPR-Bench's way: the trapezoidal rule
    (``sklearn.metrics.auc``) over the points of :func:`precision_recall_curve`
    (``[T]`` each, by decreasing threshold) preceded by sklearn's (recall 0, precision 1)
    point. Not the step-wise average precision."""
    precision, recall = _curve(precision, recall)
    precision = np.concatenate(([1.0], precision))
    recall = np.concatenate(([0.0], recall))
    return float(np.sum(np.diff(recall) * (precision[1:] + precision[:-1]) / 2))


def recall_at_100_precision(precision: np.ndarray, recall: np.ndarray) -> float:
    """R_P100: the largest recall among the points (``[T]`` each) whose precision is
    exactly 1, or 0 when there is none."""
    precision, recall = _curve(precision, recall)
    perfect = precision == 1.0
    return float(recall[perfect].max()) if perfect.any() else 0.0


def extended_precision(precision: np.ndarray, recall: np.ndarray) -> float:
    """VPR-Bench's EP = (P_R0 + R_P100) / 2 of a curve from :func:`precision_recall_curve`
    (``[T]`` each, by decreasing threshold).

    P_R0 is the precision at the highest threshold (the lowest recall). As in VPR-Bench,
    R_P100 counts only when P_R0 is 1: on a real curve a wrong match at the highest
    threshold stays accepted below it, so no point could reach precision 1 anyway.
    """
    precision, recall = _curve(precision, recall)
    first_precision = float(precision[0])
    full = recall_at_100_precision(precision, recall) if first_precision == 1.0 else 0.0
    return (first_precision + full) / 2


# The summary's metrics by the names the results table gives them, in its column order.
SUMMARY = {
    "auc_pr": auc_pr,
    "recall_at_100_precision": recall_at_100_precision,
    "extended_precision": extended_precision,
}


def summary(
    confidence: np.ndarray, correct: np.ndarray, has_positive: np.ndarray
) -> dict[str, float]:
    """Each :data:`SUMMARY` metric, by name, as a Python float, of the curve
    :func:`precision_recall_curve` gives for these ``[Nq]`` arrays."""
    precision, recall, _ = precision_recall_curve(confidence, correct, has_positive)
    return {name: metric(precision, recall) for name, metric in SUMMARY.items()}
