"""The ``matches`` rule: each query's re-ranking candidates (its retrieval's top K) and
every candidate's mutual nearest neighbour patch pairs with it
(:func:`vprflow.evaluation.rerank.candidate_pairs`), once for all the re-rankers of a
method on the same features and ``top_k``; each ``rerank`` stage scores them.

The retrieval is the method's own (:func:`vprflow.stages.retrieval.retrieve`, the ranking
its recall row is computed from, as deep as ``depth``, the recall's, or ``top_k`` if
deeper); the patch features are the re-ranker's (any backbone entry, so they may differ
from the method's). The pairs carry no threshold: ``min_similarity`` and the weighting
act when scoring, so they do not depend on any re-ranker's options.
"""

from __future__ import annotations

import logging
import time

import numpy as np
from tqdm import tqdm

from vprflow.core import stores
from vprflow.core.lazy import lazy_import
from vprflow.evaluation.rerank import candidate_pairs
from vprflow.stages.base import Job
from vprflow.stages.readers import PAIR_ARRAYS, Dataset
from vprflow.stages.retrieval import timed_retrieve

devices = lazy_import("vprflow.core.devices")
torch = lazy_import("torch")

log = logging.getLogger("vprflow")

# Reference features up to this size are read into memory once; larger sets are read
# per candidate (a query's K candidates are scattered over the database).
_IN_MEMORY_BYTES = 2 << 30


def _references_on(device, references: np.ndarray | None):
    """The in-memory reference features on ``device`` once, when it is not the CPU and
    (CUDA) they take at most half its free memory: a query's candidates are then gathered
    there instead of crossing the bus per query (the G/14 grid of a 640 x 480 image: about
    1 GB for K = 100). None otherwise."""
    if references is None or device.type == "cpu":
        return None
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        if references.nbytes > free // 2:
            return None
    return torch.from_numpy(references).to(device)


def compute_matches(job: Job) -> None:
    """Store ``retrieval_ranking [Nq, D]`` int64 (reference indices, -1 = none; ``D =
    max(depth, top_k)`` capped at the references), whose first ``K`` columns (attribute
    ``top_k``: ``top_k`` capped at ``D``) are the candidates, and their pairs as ragged flat
    arrays: candidate ``k`` of query ``q`` (``c = q K + k``) has pairs ``offsets[c] :
    offsets[c + 1]`` (``offsets [Nq K + 1]`` int64; none for a ``-1`` candidate) of
    ``query_patch``, ``candidate_patch`` (int32 row-major patch indices) and
    ``similarity`` (float32, as :func:`vprflow.evaluation.rerank.candidate_pairs` gives
    it), ordered by increasing query patch. Attributes: the features' ``grid`` and
    ``patch_size``, ``top_k``, ``depth``, ``ms_per_query`` (the matching) and
    ``search_ms_per_query`` (the retrieval)."""
    inputs, params = job.inputs, job.params
    dataset = Dataset(inputs["images"])
    n_ref, n_query = dataset.n_reference, dataset.n_query
    # The candidates, then the rest of the retrieval as deep as the recall reads.
    (retrieved, _, _), search_ms = timed_retrieve(
        dataset,
        inputs["descriptors"],
        max(params["top_k"], params["depth"]),
        inputs.get("search"),
        params.get("vote_ranking"),
    )
    features = stores.open_store(inputs["features"])
    array = features["features"]
    grid = [int(v) for v in features.attrs["grid"]]
    patch = int(features.attrs["patch_size"])
    per_image = 4 * int(np.prod(array.shape[1:]))
    references = (
        np.asarray(array[:n_ref], dtype=np.float32)
        if per_image * n_ref <= _IN_MEMORY_BYTES
        else None
    )
    device = devices.resolve_device(job.device)
    on_device = _references_on(device, references)
    top_k = min(params["top_k"], retrieved.shape[1])
    counts = np.zeros((n_query, top_k), dtype=np.int64)
    with stores.atomic_store(job.out, {"stage": "matches", "record": job.record}) as group:
        chunk = stores.rows_per_chunk(4)
        writers = {
            name: stores.RowWriter(group, name, (), dtype, chunk)
            for name, dtype in PAIR_ARRAYS.items()
        }
        started = time.perf_counter()
        for q in tqdm(range(n_query), desc="matches", unit="query"):
            # A retrieval's -1 padding trails its row: the candidates are the head's present.
            present = np.flatnonzero(retrieved[q, :top_k] >= 0)
            if not len(present):
                continue
            candidates = retrieved[q, present]
            query = np.asarray(array[n_ref + q], dtype=np.float32)
            if on_device is not None:
                stack = on_device[torch.as_tensor(candidates, device=device)]
            elif references is not None:
                stack = references[candidates]
            else:
                stack = np.stack([np.asarray(array[int(r)], dtype=np.float32) for r in candidates])
            found = candidate_pairs(
                torch.as_tensor(query.reshape(-1, query.shape[-1])).to(device),
                stack.reshape(len(candidates), -1, stack.shape[-1]),
            )
            counts[q, present] = [len(i) for i, _, _ in found]
            for column, name in enumerate(PAIR_ARRAYS):
                writers[name].append(
                    np.concatenate([pairs[column] for pairs in found]),
                    f"{name} of query {q}",
                )
        for writer in writers.values():
            writer.close()
        seconds = time.perf_counter() - started
        offsets = np.concatenate([[0], np.cumsum(counts.ravel())]).astype(np.int64)
        stores.write_array(group, "offsets", offsets)
        stores.write_array(group, "retrieval_ranking", retrieved.astype(np.int64))
        stores.set_attrs(
            group,
            grid=grid,
            patch_size=patch,
            top_k=int(top_k),
            depth=int(retrieved.shape[1]),
            ms_per_query=1000 * seconds / max(n_query, 1),
            # The retrieval's own cost, for the re-ranked row's search_ms_per_query.
            search_ms_per_query=search_ms,
        )
    log.info(
        "matched the top %d (of %d retrieved) of %d queries: %d pairs, %.1f ms a query",
        top_k,
        retrieved.shape[1],
        n_query,
        int(offsets[-1]),
        1000 * seconds / max(n_query, 1),
    )
