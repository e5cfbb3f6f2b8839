"""The recall stage (vprflow.stages.recall) against a direct ranking, retrieved and re-ranked."""

from __future__ import annotations

import numpy as np
import pytest
from toy_pipeline import N_PLACES, rerank_store, stage_path

from vprflow.core import stores
from vprflow.stages.readers import Dataset


def test_global_recall_matches_a_direct_ranking(pipeline):
    """Recall@N of a global method from a float64 brute-force L2 ranking in the test."""
    descriptors = np.asarray(
        stores.open_store(stage_path(pipeline, "descriptors", "anyloc_vlad"))["descriptors"][...],
        dtype=np.float64,
    )
    ref, query = descriptors[:N_PLACES], descriptors[N_PLACES:]
    truth = Dataset(stage_path(pipeline, "dataset")).truth()
    distances = ((query[:, None, :] - ref[None, :, :]) ** 2).sum(-1)
    order = np.argsort(distances, axis=1, kind="stable")
    # Ties closer than float32 precision would make the order arbitrary: none here.
    gaps = np.diff(np.sort(distances, axis=1), axis=1)
    assert gaps.min() > 1e-4 * distances.max()
    result = stores.open_store(stage_path(pipeline, "recall", "anyloc_vlad"))
    for n in (1, 3):
        direct = np.mean([bool(set(order[q, :n]) & set(truth[q])) for q in range(N_PLACES)])
        assert result.attrs["recall"][str(n)] == pytest.approx(direct, abs=1e-12)
    np.testing.assert_array_equal(np.asarray(result["ranking"][...])[:, :3], order[:, :3])


def test_reranked_recall_reads_the_reranked_ranking_and_states_its_cost(pipeline):
    plan, runner, _, _ = pipeline
    truth = Dataset(stage_path(pipeline, "dataset")).truth()
    for method in ("anyloc_vlad+mnn", "segvlad+ransac"):
        run = {r.method: r for r in plan.runs["toy"]}[method]
        result = stores.open_store(runner.path("recall", run.recall_key))
        reranked = rerank_store(pipeline, method)
        ranking = np.asarray(reranked["ranking"][...])
        np.testing.assert_array_equal(result["ranking"][...], ranking)
        # What was re-ordered is kept for the report's before/after montage.
        np.testing.assert_array_equal(
            result["retrieval_ranking"][...], reranked["retrieval_ranking"][...]
        )
        direct = np.mean([ranking[q, 0] in truth[q] for q in range(N_PLACES)])
        assert result.attrs["recall"]["1"] == pytest.approx(direct, abs=1e-12)
        assert result.attrs["cost"]["rerank_ms_per_query"] > 0
    retrieval = stores.open_store(stage_path(pipeline, "recall", "anyloc_vlad"))
    assert retrieval.attrs["cost"]["rerank_ms_per_query"] is None
    assert "retrieval_ranking" not in retrieval
    dim = retrieval.attrs["descriptor_dim"]
    assert retrieval.attrs["cost"]["descriptor_bytes_per_image"] == 4 * dim
