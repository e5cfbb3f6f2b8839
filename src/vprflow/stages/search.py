"""The ``search`` rule: every query segment's nearest reference segments, one shard of
reference images per job, merged into the exact global top-k by :func:`merge_search`.

A job holds one shard of reference segments and one block of query segments at a
time, so its memory is bounded by the shard and block sizes, not by the database.
Results are listed nearest first with exact distance ties broken by increasing
reference segment index, in every shard and after the merge, so a sharded search
gives the same lists as an unsharded one (docs/methods.md §8). Rows of an
approximate index that found fewer than k segments end in index ``-1`` with
distance ``inf``; voting ignores them.
"""

from __future__ import annotations

import logging

import numpy as np
from tqdm import tqdm

from vprflow.core import stores
from vprflow.core.paths import shard_layout
from vprflow.search.indexes import search_index
from vprflow.search.topk import merge_knn
from vprflow.stages.base import Job, stage_attrs
from vprflow.stages.readers import Dataset

log = logging.getLogger("vprflow")

# Query segments searched (and merged) per block: 65,536 x 50 results is 40 MB.
QUERY_BLOCK = 1 << 16


def compute_search(job: Job) -> None:
    """Top-``top_segments`` reference segments of the job's reference images
    (``start..stop``) for every query segment: ``distances [Sq, k']`` float32,
    ``indices [Sq, k']`` int64 (global reference segment rows), k' = min(top_segments,
    segments in the shard)."""
    record, params = job.record, job.params
    index = search_index(params["index"])
    dataset = Dataset(job.inputs["images"])
    references = job.images(dataset.n_reference)
    start, stop = references.start, references.stop
    group = stores.open_store(job.inputs["descriptors"])
    offsets = np.asarray(group["descriptors_offsets"][...])
    low, high = int(offsets[start]), int(offsets[stop])
    split, total = int(offsets[dataset.n_reference]), int(offsets[-1])
    vectors = group["descriptors"]
    database = np.asarray(vectors[low:high], dtype=np.float32)
    k = min(params["top_segments"], len(database))
    attrs = {**stage_attrs("search", record, references), "rows": [low, high]}
    with stores.atomic_store(job.out, attrs) as result:
        found = _list_writers(result, k)
        for block in tqdm(range(split, total, QUERY_BLOCK), desc="search", unit="block"):
            queries = np.asarray(vectors[block : min(block + QUERY_BLOCK, total)], np.float32)
            if k:
                distances, indices = index.search(
                    database, queries, k, params["params"], job.device
                )
                found_any = indices >= 0  # approximate indexes pad short rows with -1
                indices = np.where(found_any, indices + low, -1)
                distances = np.where(found_any, distances, np.inf).astype(np.float32)
                distances, indices = merge_knn([(distances, indices)], k)
            else:  # a shard of images without segments retrieves nothing
                distances = np.zeros((len(queries), 0), np.float32)
                indices = np.zeros((len(queries), 0), np.int64)
            found["distances"].append(distances)
            found["indices"].append(indices)
        for writer in found.values():
            writer.close()
    log.info("searched %d query segments in reference segments %d..%d", total - split, low, high)


def merge_search(shard_paths: list[str], record: dict, out: str) -> None:
    """The exact top-k over all shards: per query segment the ``top_segments`` best of
    every shard's lists by (distance, index), read one query block at a time."""
    k = record["params"]["top_segments"]
    shards = [stores.open_store(p) for p in shard_paths]
    n_rows = shards[0]["distances"].shape[0]
    k_total = min(k, sum(s["distances"].shape[1] for s in shards))
    attrs = {"stage": "search", "record": record, "shards": shard_layout(shard_paths)}
    with stores.atomic_store(out, attrs) as result:
        found = _list_writers(result, k_total)
        for block in tqdm(range(0, n_rows, QUERY_BLOCK), desc="merge", unit="block"):
            rows = slice(block, min(block + QUERY_BLOCK, n_rows))
            # Shard by shard, keeping the best k: memory is two lists per row, whatever
            # the number of shards.
            distances, indices = shards[0]["distances"][rows], shards[0]["indices"][rows]
            for shard in shards[1:]:
                distances, indices = merge_knn(
                    [(distances, indices), (shard["distances"][rows], shard["indices"][rows])],
                    k_total,
                )
            found["distances"].append(distances)
            found["indices"].append(indices)
        for writer in found.values():
            writer.close()


def _list_writers(group, k: int) -> dict[str, stores.RowWriter]:
    """Writers of the ``[Sq, k]`` segment lists: float32 distances, int64 indices."""
    chunk = stores.rows_per_chunk(12 * k)
    return {
        "distances": stores.RowWriter(group, "distances", (k,), np.float32, chunk),
        "indices": stores.RowWriter(group, "indices", (k,), np.int64, chunk),
    }
