"""The ``recall`` rule: rank the references for every query and compute Recall@N and
mAP@N (none for a dataset without ground truth: ``ground_truth: {kind: none}``)."""

from __future__ import annotations

import logging

import numpy as np

from vprflow import stores
from vprflow.stages.dataset import Dataset

log = logging.getLogger("vprflow")


def evaluate(
    dataset_path: str,
    descriptors_path: str,
    record: dict,
    out: str,
    search_path: str | None = None,
    exact_search_path: str | None = None,
) -> None:
    """Rank the references for every query and compute Recall@N.

    Per-segment descriptors are ranked by voting over the segment lists of the
    ``search`` stage (``search_path``); global ones by exact search here. With an
    approximate segment search, ``exact_search_path`` holds an exact search of the
    same descriptors: its Recall@N is stored too (``recall_exact``), so the table can
    say what the approximation cost.
    """
    from vprflow.knn.flat import flat_knn
    from vprflow.recall import correct_at, counted_queries, map_at, recall_at
    from vprflow.stages.search import read_search
    from vprflow.voting import image_of_segment, scored_vote_ranking

    params = record["params"]
    dataset = Dataset(dataset_path)
    group = stores.open_store(descriptors_path)
    n_ref, n_query = dataset.n_reference, dataset.n_query
    top_k = min(params["top_k"], n_ref)
    truth = dataset.truth()
    has_truth = dataset.has_ground_truth
    denominator = params["denominator"]
    recall_exact = None
    if group.attrs["kind"] == "segments":
        if search_path is None:
            raise ValueError(f"{descriptors_path}: per-segment descriptors need a search input")
        offsets = np.asarray(group["descriptors_offsets"][...])
        split = int(offsets[n_ref])
        owner = image_of_segment(offsets)

        def voted(path: str) -> np.ndarray:
            distances, indices = read_search(path)
            return scored_vote_ranking(
                distances,
                indices,
                owner[split:] - n_ref,
                owner[:split],
                n_query,
                n_ref,
                top_k,
                params["vote_ranking"],
            )

        # Scores: votes (higher is better).
        ranking, scores = voted(search_path)
        if exact_search_path is not None and has_truth:
            exact_ranking = voted(exact_search_path)[0]
            recall_exact = recall_at(exact_ranking, truth, params["recall_at"], denominator)
    else:
        vectors = np.asarray(group["descriptors"][...])
        # Scores: squared L2 distances (lower is better).
        scores, ranking = flat_knn(vectors[:n_ref], vectors[n_ref:], top_k)
    # N beyond the number of references is kept: it equals Recall@n_ref.
    recalls, maps = {}, {}
    evaluated = np.zeros(n_query, dtype=bool)
    if has_truth:
        recalls = recall_at(ranking, truth, params["recall_at"], denominator)
        maps = map_at(ranking, truth, params["recall_at"], denominator)
        evaluated = counted_queries(truth, denominator)
    ranked = (ranking >= 0).sum(axis=1)
    with stores.atomic_store(out, {"stage": "recall", "record": record}) as result:
        result.attrs.update(
            recall={str(n): v for n, v in recalls.items()},
            map={str(n): v for n, v in maps.items()},
            denominator=denominator,
            score="votes" if group.attrs["kind"] == "segments" else "squared_l2",
            recall_exact=None
            if recall_exact is None
            else {str(n): v for n, v in recall_exact.items()},
            n_queries=int(evaluated.sum()),
            descriptor_dim=int(group.attrs["dim"]),
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
    if has_truth:
        log.info("recall: %s, mAP: %s (over %d queries)", recalls, maps, int(evaluated.sum()))
    else:
        log.info("no ground truth: ranked %d queries, no recall computed", n_query)
