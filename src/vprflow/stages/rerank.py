"""The ``rerank`` rule: re-order each query's top-K retrieved references by a re-ranker's
score of their local matches (:mod:`vprflow.evaluation.rerank`), read from the
``matches`` store (:mod:`vprflow.stages.matches`: the retrieval, the candidates and
their mutual nearest neighbour patch pairs), which the re-rankers of a method on the
same features and ``top_k`` share.

The re-ranked ranking is the re-ordered top K followed by the rest of the retrieval in
its order, so a re-ranker shallower than the table's deepest Recall@N leaves the deeper
recall as the retrieval's instead of truncating it.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from tqdm import tqdm

from vprflow.core import stores
from vprflow.evaluation.rerank import pair_scorer, rerank, reranker
from vprflow.stages.base import Job
from vprflow.stages.readers import Matches

log = logging.getLogger("vprflow")


def compute_rerank(job: Job) -> None:
    """Store ``ranking [Nq, D]`` (reference indices, -1 = none; the top ``K = top_k``
    re-ordered, then the rest of the retrieval), ``scores [Nq, D]`` (the re-ranker's,
    higher is better; see :func:`vprflow.evaluation.rerank.rerank` for the entries not
    re-ranked) and the retrieval they re-order (``retrieval_ranking [Nq, D]``), all as
    deep as the matches store's retrieval. ``ms_per_query`` is the re-ranking's cost: the
    matches store's matching plus this scoring; ``search_ms_per_query`` the retrieval's
    (the matches store's)."""

    params = job.params
    matches = Matches(job.inputs["matches"])
    retrieved = matches.retrieval_ranking
    n_query = len(retrieved)
    # Checks every option now: a bad one fails even with no candidate.
    score = pair_scorer(params["kind"], params["options"], matches.grid, matches.patch)
    ranking = np.full_like(retrieved, -1)
    scores = np.zeros(retrieved.shape)  # padding (rank -1) scores 0, as in voting

    def scored(pairs: list) -> np.ndarray | None:
        return score(pairs) if pairs else None

    started = time.perf_counter()
    # Queries are scored on job.threads threads, a block at a time: RANSAC's fit is
    # OpenCV's, one core a fit, and releases the GIL; each score depends on its own
    # pairs and seed alone, so the threads change no result. The store is read in order.
    block = 64 * job.threads
    with (
        ThreadPoolExecutor(job.threads) as pool,
        tqdm(total=n_query, desc=f"rerank ({params['kind']})", unit="query") as bar,
    ):
        for first in range(0, n_query, block):
            queries = range(first, min(first + block, n_query))
            found = pool.map(scored, [matches.pairs(q) for q in queries])
            for q, query_scores in zip(queries, found, strict=True):
                if query_scores is None:
                    ranking[q] = retrieved[q]
                else:
                    ranking[q], scores[q] = rerank(retrieved[q], query_scores)
            bar.update(len(queries))
    ms = 1000 * (time.perf_counter() - started) / max(n_query, 1)
    attrs = matches.group.attrs
    with stores.atomic_store(job.out, {"stage": "rerank", "record": job.record}) as group:
        stores.set_attrs(
            group,
            score=reranker(params["kind"]).score,
            # What the re-ranked row costs beyond its retrieval: matching and scoring.
            ms_per_query=attrs["ms_per_query"] + ms,
            # The retrieval's own cost, for the re-ranked row's search_ms_per_query.
            search_ms_per_query=attrs["search_ms_per_query"],
            top_k=matches.top_k,
            depth=int(retrieved.shape[1]),
        )
        stores.write_array(group, "ranking", ranking.astype(np.int64))
        stores.write_array(group, "scores", scores.astype(np.float64))
        stores.write_array(group, "retrieval_ranking", retrieved.astype(np.int64))
    log.info(
        "re-ranked the top %d (of %d retrieved) of %d queries: scored in %.1f ms a query "
        "(%.1f with the matching)",
        matches.top_k,
        retrieved.shape[1],
        n_query,
        ms,
        attrs["ms_per_query"] + ms,
    )
