"""The matches stage (vprflow.stages.matches): each candidate's mutual patch pairs, as the
rerank stage scores them."""

from __future__ import annotations

import numpy as np
from toy_pipeline import N_PLACES, rerank_store, stage_path

from vprflow.core import stores
from vprflow.evaluation.rerank import reranker


def test_the_matches_store_holds_each_candidates_mutual_pairs_and_rerank_scores_them(pipeline):
    """segvlad+ransac (top 100 of 6 references, min_similarity 0.5): the matches store's
    candidates are the retrieval's, each candidate's pairs all those of
    mutual_nearest_neighbours on the features store (min_similarity acts when scoring),
    and the rerank store's scores those of ransac_inliers over the pairs it keeps."""
    from vprflow.evaluation.rerank import mutual_nearest_neighbours, patch_centres, ransac_inliers
    from vprflow.stages.readers import Matches

    plan, runner, _, _ = pipeline
    run = {r.method: r for r in plan.runs["toy"]}["segvlad+ransac"]
    rerank = plan.get(*plan.get("recall", run.recall_key).inputs["rerank"])
    matches = Matches(runner.path(*rerank.inputs["matches"]))
    reranked = rerank_store(pipeline, "segvlad+ransac")
    features = stores.open_store(stage_path(pipeline, "features", "segvlad"))
    patches = np.asarray(features["features"][...], dtype=np.float32)
    patches = patches.reshape(len(patches), -1, patches.shape[-1])
    assert matches.grid == tuple(features.attrs["grid"]) and matches.top_k == N_PLACES
    np.testing.assert_array_equal(matches.retrieval_ranking, reranked["retrieval_ranking"][...])
    settings = reranker("ransac").settings(rerank.record["params"]["options"])
    assert settings["min_similarity"] == 0.5
    centres = patch_centres(*matches.grid, matches.patch)
    pixels = settings["threshold"] * matches.patch
    fit = {k: settings[k] for k in ("seed", "model", "max_iters", "confidence")}
    for q in range(N_PLACES):
        candidates = matches.candidates(q)
        np.testing.assert_array_equal(candidates, matches.retrieval_ranking[q, :N_PLACES])
        pairs = matches.pairs(q)
        assert len(pairs) == len(candidates)
        scores = np.zeros(len(candidates))
        for k, (r, stored) in enumerate(zip(candidates, pairs, strict=True)):
            i, j, similarity = direct = mutual_nearest_neighbours(patches[N_PLACES + q], patches[r])
            for got, want in zip(stored, direct, strict=True):
                np.testing.assert_array_equal(got, want)
            kept = similarity >= settings["min_similarity"]
            scores[k] = ransac_inliers(centres[i[kept]], centres[j[kept]], pixels, **fit)
        row = np.asarray(reranked["ranking"][q])
        order = np.argsort(-scores, kind="stable")
        np.testing.assert_array_equal(row[: len(candidates)], candidates[order])
        np.testing.assert_array_equal(reranked["scores"][q, : len(candidates)], scores[order])
    # Read a few pairs a block (each query's at least): the same pairs, in any order.
    small = Matches(runner.path(*rerank.inputs["matches"]))
    small._block = 5
    for q in [*range(N_PLACES), 0, N_PLACES - 1, 1]:
        for got, want in zip(small.pairs(q), matches.pairs(q), strict=True):
            for a, b in zip(got, want, strict=True):
                np.testing.assert_array_equal(a, b)
    cost = reranked.attrs["ms_per_query"] - matches.group.attrs["ms_per_query"]
    assert cost > 0  # the scoring's own time, beside the matching's
    assert reranked.attrs["search_ms_per_query"] == matches.group.attrs["search_ms_per_query"]
