"""The rerank stage (vprflow.stages.rerank) against directly counted matches."""

from __future__ import annotations

import numpy as np
from toy_pipeline import N_PLACES, rerank_store, stage_path

from vprflow.core import stores
from vprflow.stages.jobs import Job, run_job


def test_reranked_rows_sort_the_retrieval_top_k_by_directly_counted_mutual_matches(pipeline):
    """anyloc_vlad+mnn: each candidate's score is the number of mutual nearest patch
    pairs, counted here in float64 with loops; the order is the retrieval's top 4
    sorted by that count, ties kept in retrieval order."""
    reranked = rerank_store(pipeline, "anyloc_vlad+mnn")
    features = stores.open_store(stage_path(pipeline, "features", "anyloc_vlad"))
    patches = np.asarray(features["features"][...], dtype=np.float64)
    patches = patches.reshape(len(patches), -1, patches.shape[-1])
    retrieved = np.asarray(reranked["retrieval_ranking"][...])
    recall = stores.open_store(stage_path(pipeline, "recall", "anyloc_vlad"))
    # As deep as the retrieval's ranking; the top 4 re-ordered, the rest kept in order.
    assert retrieved.shape == (N_PLACES, N_PLACES)
    np.testing.assert_array_equal(retrieved, np.asarray(recall["ranking"][...]))
    np.testing.assert_array_equal(reranked["ranking"][:, 4:], retrieved[:, 4:])
    retrieved = retrieved[:, :4]

    def mutual_pairs(a, b):
        sim = a @ b.T
        return sum(
            1
            for i in range(len(a))
            for j in range(len(b))
            if sim[i, j] == sim[i].max() and sim[i, j] == sim[:, j].max()
        )

    for q in range(N_PLACES):
        counts = [mutual_pairs(patches[N_PLACES + q], patches[r]) for r in retrieved[q]]
        order = sorted(range(4), key=lambda c: -counts[c])  # stable: retrieval order on ties
        np.testing.assert_array_equal(reranked["ranking"][q, :4], retrieved[q][order])
        np.testing.assert_array_equal(reranked["scores"][q, :4], np.array(counts)[order])
    assert reranked.attrs["score"] == "matches"


def test_reranking_on_one_thread_stores_what_two_threads_store(pipeline, tmp_path):
    """The rerank stage scores queries on job.threads threads (the pipeline runs 2):
    one thread stores the same ranking and scores."""
    plan, runner, _, _ = pipeline
    for method in ("anyloc_vlad+mnn", "segvlad+ransac"):
        run = {r.method: r for r in plan.runs["toy"]}[method]
        stage = plan.get(*plan.get("recall", run.recall_key).inputs["rerank"])
        inputs = {name: runner.path(*ref) for name, ref in stage.inputs.items()}
        out = str(tmp_path / f"{stage.key}.zarr")
        run_job(Job(stage.record, inputs, out, run={"device": "cpu"}, threads=1))
        one, two = stores.open_store(out), rerank_store(pipeline, method)
        for name in ("ranking", "scores", "retrieval_ranking"):
            np.testing.assert_array_equal(one[name][...], two[name][...])
