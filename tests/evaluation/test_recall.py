"""Recall@N (REFERENCE.md section 2 step 9) against a direct loop, mAP@N against the
published average precision, and which queries the denominator counts. Results are
exact fractions, compared with a 1e-12 absolute tolerance."""

from __future__ import annotations

import numpy as np
import pytest

from vprflow.evaluation.recall import average_precision_at, correct_at, map_at, recall_at


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


# ------------------------------------------------------------------ mAP@N and the denominator


def published_ap(retrieved: list[bool]) -> float:
    """Revisit-Anything's calculate_ap, as its code reads."""
    relevant = sum(retrieved)
    if relevant == 0:
        return 0.0
    hits, total = 0, 0.0
    for i, ok in enumerate(retrieved, start=1):
        if ok:
            hits += 1
            total += hits / i
    return total / relevant


def test_map_at_n_equals_the_published_average_precision():
    rng = np.random.default_rng(3)
    n_ref, n_query = 30, 40
    ranking = np.array([rng.permutation(n_ref)[:12] for _ in range(n_query)])
    ranking[3, 8:] = -1  # a short (voted) ranking
    truth = [np.sort(rng.choice(n_ref, rng.integers(0, 6), replace=False)) for _ in range(n_query)]
    truth[5] = np.zeros(0, np.int64)
    for n in (1, 5, 10):
        ap = average_precision_at(ranking, truth, n)
        for q in range(n_query):
            retrieved = [int(r) in set(truth[q].tolist()) for r in ranking[q, :n] if r >= 0]
            assert ap[q] == pytest.approx(published_ap(retrieved), abs=1e-12)
        with_positives = [q for q in range(n_query) if len(truth[q])]
        assert map_at(ranking, truth, [n])[n] == pytest.approx(
            np.mean([ap[q] for q in with_positives]), abs=1e-12
        )
        assert map_at(ranking, truth, [n], "all")[n] == pytest.approx(np.mean(ap), abs=1e-12)


def test_the_denominator_counts_queries_without_positives_as_misses_when_all():
    ranking = np.array([[0, 1], [1, 0], [2, 0], [0, 2]])
    truth = [np.array([0]), np.array([0]), np.zeros(0, np.int64), np.array([2])]
    assert recall_at(ranking, truth, [1, 2]) == {1: pytest.approx(1 / 3), 2: 1.0}
    assert recall_at(ranking, truth, [1, 2], "all") == {1: 0.25, 2: 0.75}
    with pytest.raises(ValueError, match="unknown denominator"):
        recall_at(ranking, truth, [1], "some")


# ------------------------------------------------------------------ queries without a positive


def toy_stores(tmp_path, truth: list[list[int]], n_ref: int = 3):
    """A dataset store (``truth`` per query, rule ``frame_window:+-0``) and a global
    descriptors store in which query ``q`` is nearest reference ``q % n_ref``."""
    from vprflow.core import stores

    n_query = len(truth)
    names = [f"ref/r{i}.jpg" for i in range(n_ref)] + [f"query/q{i}.jpg" for i in range(n_query)]
    dataset, descriptors = tmp_path / "dataset.zarr", tmp_path / "descriptors.zarr"
    with stores.atomic_store(dataset, {"stage": "dataset"}) as group:
        group.attrs.update(
            n_reference=n_ref,
            n_query=n_query,
            ground_truth_rule="frame_window:+-0",
            exif_orientation=True,
        )
        stores.write_array(group, "paths", np.array([f"toy/{n}" for n in names]))
        stores.write_array(group, "names", np.array(names))
        flat = [r for refs in truth for r in refs]
        stores.write_array(group, "truth", np.array(flat, dtype=np.int64))
        offsets = np.r_[0, np.cumsum([len(refs) for refs in truth])].astype(np.int64)
        stores.write_array(group, "truth_offsets", offsets)
    vectors = np.eye(n_ref, dtype=np.float32)
    vectors = np.concatenate([vectors, vectors[np.arange(n_query) % n_ref] * 0.9])
    with stores.atomic_store(descriptors, {"stage": "descriptors"}) as group:
        group.attrs.update(kind="global", dim=n_ref)
        stores.write_array(group, "descriptors", vectors)
    return str(dataset), str(descriptors)


def test_queries_without_positive_are_listed_in_order():
    from vprflow.evaluation.recall import queries_without_positive

    truth = [np.array([0]), np.zeros(0, np.int64), np.array([1, 2]), np.zeros(0, np.int64)]
    assert queries_without_positive(truth).tolist() == [1, 3]


@pytest.mark.parametrize(
    ("denominator", "counted", "fate"),
    [
        ("with_positives", 3, "left out of Recall@N and mAP@N"),
        ("all", 5, "counted as misses"),
    ],
)
def test_the_recall_store_and_table_count_queries_without_positive_and_the_log_names_them(
    tmp_path, caplog, denominator, counted, fate
):
    # A query whose positions were damaged had no positive and vanished from n_queries
    # without a word (with_positives), or sank recall unexplained (all).
    import csv

    from vprflow.core import stores
    from vprflow.stages.jobs import Job
    from vprflow.stages.recall import compute_recall
    from vprflow.stages.report import write_recall_csv

    dataset, descriptors = toy_stores(tmp_path, [[0], [], [2], [], [1]])
    record = {"params": {"denominator": denominator, "depth": 3, "recall_at": [1, 2]}}
    out = tmp_path / "recall.zarr"
    with caplog.at_level("WARNING", logger="vprflow"):
        compute_recall(Job(record, {"dataset": dataset, "descriptors": descriptors}, str(out)))
    attrs = stores.open_store(out).attrs
    assert attrs["n_queries"] == counted
    assert attrs["n_queries_without_positive"] == 2
    assert (
        f"2 of 5 queries have no positive under frame_window:+-0 ({fate}): "
        "1 query/q1.jpg, 3 query/q3.jpg" in caplog.text
    )
    table = tmp_path / "recall.csv"
    write_recall_csv("toy", [{"method": "m", "params": {}}], [str(out)], str(table))
    with open(table) as f:
        (row,) = list(csv.DictReader(f))
    assert row["n_queries"] == str(counted) and row["n_queries_without_positive"] == "2"
