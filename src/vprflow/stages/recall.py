"""The ``recall`` rule: rank the references for every query and compute Recall@N and
mAP@N (none for a dataset without ground truth: ``ground_truth: {kind: none}``)."""

from __future__ import annotations

import logging

import numpy as np

from vprflow.core import stores
from vprflow.evaluation.precision_recall import summary
from vprflow.evaluation.recall import (
    COST_COLUMNS,
    correct_at,
    counted_queries,
    map_at,
    queries_without_positive,
    recall_at,
)
from vprflow.stages.base import Job
from vprflow.stages.readers import Dataset
from vprflow.stages.retrieval import retrieve, timed_retrieve, top1_matches

log = logging.getLogger("vprflow")


# What a query costs, as the recall store's `cost` and the results table name it.
def descriptor_bytes_per_image(descriptors, n_images: int) -> float:
    """Bytes of descriptors an image costs in the database, as stored (``descriptors``:
    the store's array): the vector of a global method; every segment's vector of a
    per-segment one (mean over images)."""
    return float(np.prod(descriptors.shape)) * descriptors.dtype.itemsize / max(n_images, 1)


def log_without_positive(dataset: Dataset, queries: np.ndarray, denominator: str) -> None:
    """Name the queries without a positive (the first ten) in the recall log, and what
    the denominator made of them."""
    if not len(queries):
        return
    fate = {
        "with_positives": "left out of Recall@N and mAP@N",
        "all": "counted as misses",
    }[denominator]
    names = [dataset.names[dataset.n_reference + int(q)] for q in queries[:10]]
    log.warning(
        "%d of %d queries have no positive under %s (%s): %s%s",
        len(queries),
        dataset.n_query,
        dataset.group.attrs["ground_truth_rule"],
        fate,
        ", ".join(f"{int(q)} {name}" for q, name in zip(queries, names, strict=False)),
        ", ..." if len(queries) > len(names) else "",
    )


def compute_recall(job: Job) -> None:
    """Rank the references for every query (:func:`retrieve`, over the ``search`` input
    for per-segment descriptors, or the re-ranked lists of a ``rerank`` input) and
    compute Recall@N, mAP@N and the precision-recall summary of the top-1 matches, by the
    ``dataset`` input's ground truth.

    With an approximate segment search, the ``exact_search`` input is an exact search of
    the same descriptors: its Recall@N is stored too (``recall_exact``), so the table
    can say what the approximation cost.
    """

    record, params = job.record, job.params
    descriptors_path = job.inputs["descriptors"]
    search_path = job.inputs.get("search")
    exact_search_path = job.inputs.get("exact_search")
    rerank_path = job.inputs.get("rerank")
    dataset = Dataset(job.inputs["dataset"])
    n_ref, n_query = dataset.n_reference, dataset.n_query
    truth = dataset.truth()
    has_truth = dataset.has_ground_truth
    denominator = params["denominator"]
    recall_exact = None
    vote_ranking = params.get("vote_ranking")
    rerank_ms = None
    depth = params["depth"]
    if rerank_path is None:
        (ranking, scores, score_kind), search_ms = timed_retrieve(
            dataset, descriptors_path, depth, search_path, vote_ranking
        )
    else:
        # The rerank stage ran (and timed) the retrieval it re-ordered.
        reranked = stores.open_store(rerank_path)
        ranking = np.asarray(reranked["ranking"][...])
        scores = np.asarray(reranked["scores"][...])
        score_kind = reranked.attrs["score"]
        search_ms, rerank_ms = reranked.attrs["search_ms_per_query"], reranked.attrs["ms_per_query"]
    if exact_search_path is not None and has_truth:
        exact = retrieve(dataset, descriptors_path, depth, exact_search_path, vote_ranking)
        exact_ranking = exact[0]
        recall_exact = recall_at(exact_ranking, truth, params["recall_at"], denominator)
    # N beyond the number of references is kept: it equals Recall@n_ref.
    recalls, maps, precision = {}, {}, {}
    evaluated = np.zeros(n_query, dtype=bool)
    without_positive = None  # no ground truth: no query is judged at all
    if has_truth:
        without_positive = queries_without_positive(truth)
        log_without_positive(dataset, without_positive, denominator)
        recalls = recall_at(ranking, truth, params["recall_at"], denominator)
        maps = map_at(ranking, truth, params["recall_at"], denominator)
        evaluated = counted_queries(truth, denominator)
        matches = top1_matches(ranking, scores, score_kind, truth, evaluated)
        # No correct top-1 match: VPR-Bench's recall is 0 / 0; the cells stay empty.
        if matches is not None:
            precision = summary(*matches)
    ranked = (ranking >= 0).sum(axis=1)
    descriptors = stores.open_store(descriptors_path)
    bytes_per_image = descriptor_bytes_per_image(descriptors["descriptors"], n_ref + n_query)
    with stores.atomic_store(job.out, {"stage": "recall", "record": record}) as result:
        stores.set_attrs(
            result,
            recall={str(n): v for n, v in recalls.items()},
            map={str(n): v for n, v in maps.items()},
            precision_recall=precision,
            denominator=denominator,
            score=score_kind,
            recall_exact=None
            if recall_exact is None
            else {str(n): v for n, v in recall_exact.items()},
            n_queries=int(evaluated.sum()),
            # Under either denominator: left out (with_positives) or misses (all).
            n_queries_without_positive=None if without_positive is None else len(without_positive),
            descriptor_dim=int(descriptors.attrs["dim"]),
            # What a query costs: not part of the results (the ms vary run to run).
            cost=dict(zip(COST_COLUMNS, (bytes_per_image, search_ms, rerank_ms), strict=True)),
            # Queries ranking fewer references than the largest N (or than all of them):
            # SegVLAD ranks only voted images, and a missing rank counts as a miss.
            n_short_rankings=int(
                (evaluated & (ranked < min(max(params["recall_at"]), n_ref))).sum()
            ),
            ground_truth_rule=dataset.group.attrs["ground_truth_rule"],
        )
        stores.write_array(result, "ranking", ranking.astype(np.int64))
        stores.write_array(result, "scores", np.asarray(scores, dtype=np.float64))
        stores.write_array(result, "first_correct", correct_at(ranking, truth))
        if rerank_path is not None:
            # What the re-ranker re-ordered, for the report's before/after montage.
            stores.write_array(result, "retrieval_ranking", reranked["retrieval_ranking"][...])
    if has_truth:
        log.info("recall: %s, mAP: %s (over %d queries)", recalls, maps, int(evaluated.sum()))
    else:
        log.info("no ground truth: ranked %d queries, no recall computed", n_query)
