"""The ``rerank`` rule: re-order each query's top-K retrieved references by local
matches between dense patch features (:mod:`vprflow.evaluation.rerank`).

The retrieval is the method's own (:func:`vprflow.stages.recall.retrieve`, the ranking
its recall row is computed from, as deep as ``depth``, the recall's, or ``top_k`` if
deeper); the patch features are the re-ranker's (any backbone entry, so they may differ
from the method's). The re-ranked ranking is the re-ordered top K followed by the rest
of the retrieval in its order, so a re-ranker shallower than the table's deepest
Recall@N leaves the deeper recall as the retrieval's instead of truncating it.
"""

from __future__ import annotations

import logging
import time

import numpy as np
from tqdm import tqdm

from vprflow.core import stores
from vprflow.core.registry import reranker
from vprflow.stages.base import Job
from vprflow.stages.dataset import Dataset
from vprflow.stages.recall import timed_retrieve

log = logging.getLogger("vprflow")

# Reference features up to this size are read into memory once; larger sets are read
# per candidate (a query's K candidates are scattered over the database).
_IN_MEMORY_BYTES = 2 << 30


def rerank_stage(job: Job) -> None:
    """Store ``ranking [Nq, D]`` (reference indices, -1 = none; the top ``K = top_k``
    re-ordered, then the rest of the retrieval), ``scores [Nq, D]`` (the re-ranker's,
    higher is better; see :func:`vprflow.evaluation.rerank.rerank` for the entries not re-ranked)
    and the retrieval they re-order (``retrieval_ranking [Nq, D]``), ``D = max(depth,
    top_k)`` capped at the references; ``ms_per_query`` times the re-ranking alone,
    ``search_ms_per_query`` the retrieval."""
    from vprflow.core.devices import resolve_device
    from vprflow.evaluation.rerank import rerank, rerank_scores

    inputs, record, params = job.inputs, job.record, job.params
    dataset = Dataset(inputs["images"])
    n_ref = dataset.n_reference
    (retrieved, _, _), search_ms = timed_retrieve(
        dataset,
        inputs["descriptors"],
        max(params["top_k"], params["depth"]),
        inputs.get("search"),
        params.get("vote_ranking"),
    )
    features = stores.open_store(inputs["features"])
    array = features["features"]
    grid = tuple(int(v) for v in features.attrs["grid"])
    patch = int(features.attrs["patch_size"])
    per_image = 4 * int(np.prod(array.shape[1:]))
    in_memory = per_image * n_ref <= _IN_MEMORY_BYTES
    references = np.asarray(array[:n_ref], dtype=np.float32) if in_memory else None
    torch_device = resolve_device(job.device)
    options = params["options"]
    ranking = np.full_like(retrieved, -1)
    scores = np.zeros(retrieved.shape)  # padding (rank -1) scores 0, as in voting
    started = time.perf_counter()
    top_k = min(params["top_k"], retrieved.shape[1])
    for q in tqdm(range(dataset.n_query), desc=f"rerank ({params['kind']})", unit="query"):
        # A retrieval's -1 padding trails its row: the candidates are the head's present.
        candidates = retrieved[q, :top_k][retrieved[q, :top_k] >= 0]
        if not len(candidates):
            ranking[q] = retrieved[q]
            continue
        query = np.asarray(array[n_ref + q], dtype=np.float32)
        if references is not None:
            stack = references[candidates]
        else:
            stack = np.stack([np.asarray(array[int(r)], dtype=np.float32) for r in candidates])
        found = rerank_scores(
            query.reshape(-1, query.shape[-1]),
            stack.reshape(len(candidates), -1, stack.shape[-1]),
            grid,
            patch,
            params["kind"],
            device=torch_device,
            **options,
        )
        ranking[q], scores[q] = rerank(retrieved[q], found)
    seconds = time.perf_counter() - started
    with stores.atomic_store(job.out, {"stage": "rerank", "record": record}) as group:
        group.attrs.update(
            score=reranker(params["kind"]).score,
            ms_per_query=1000 * seconds / max(dataset.n_query, 1),
            # The retrieval's own cost, for the re-ranked row's search_ms_per_query.
            search_ms_per_query=search_ms,
            top_k=int(top_k),
            depth=int(retrieved.shape[1]),
        )
        stores.write_array(group, "ranking", ranking.astype(np.int64))
        stores.write_array(group, "scores", scores.astype(np.float64))
        stores.write_array(group, "retrieval_ranking", retrieved.astype(np.int64))
    log.info(
        "re-ranked the top %d (of %d retrieved) of %d queries in %.1f ms a query",
        top_k,
        retrieved.shape[1],
        dataset.n_query,
        1000 * seconds / max(dataset.n_query, 1),
    )
