"""The ``descriptors`` rule: each method's descriptors of every image.

What a method computes per image is its aggregator entry's ``compute``
(:mod:`vprflow.aggregation.aggregators`), run by
:func:`vprflow.stages.image_descriptors.image_descriptor` over the
inputs the entry needs, the same way for every aggregator.
"""

from __future__ import annotations

import itertools
import logging
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from contextlib import nullcontext

import numpy as np
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from vprflow.aggregation.aggregators import aggregator
from vprflow.core import stores
from vprflow.stages.base import Job, stage_attrs
from vprflow.stages.image_descriptors import image_descriptor
from vprflow.stages.readers import Dataset, read_pca

log = logging.getLogger("vprflow")


def compute_descriptors(job: Job) -> None:
    """Per-image descriptors of one method over the job's images, as its aggregator's
    entry (:data:`vprflow.aggregation.aggregators.AGGREGATORS`) computes them.

    Aggregators with ``output="segments"`` write a ragged ``descriptors`` array (one
    row per segment, offsets per image), projected by the ``pca`` input when there is
    one; ``output="global"`` aggregators write ``descriptors [n, dim]``.

    Each image is computed with one BLAS thread: per-image products are small, and BLAS
    threads on them cost more than they save (up to 10x on a busy machine, the threads
    waiting for each other). With ``job.threads`` above 1, images are computed on a
    pool of that many threads or on the calling thread, whichever is faster
    (:func:`fastest_in_order`). The stored values are the same for any ``threads``
    (OpenBLAS rounds a product differently with a different number of its threads).
    """
    inputs, params, threads = job.inputs, job.params, job.threads
    agg = aggregator(params["aggregator"])
    dataset = Dataset(inputs["images"])
    images = job.images(dataset.n_images)
    describe = image_descriptor(agg, params, inputs)
    by_segment = agg.output == "segments"
    pca = read_pca(inputs["pca"]) if "pca" in inputs else None
    # An aggregator that offers a storage precision has it among its options (SegVLAD:
    # segvlad.store_dtype); the others store float32.
    dtype = np.dtype(params["store_dtype"] if "store_dtype" in params else np.float32)
    attrs = {**stage_attrs("descriptors", job.record, images), "kind": agg.output}

    def rows_of(data: tuple) -> np.ndarray:
        rows = describe.compute(*data)
        rows = rows if by_segment else rows[None]
        return rows if pca is None else pca.transform(rows)

    with (
        stores.atomic_store(job.out, attrs) as group,
        threadpool_limits(limits=1),
        # A pool of one thread would only add hand-overs.
        ThreadPoolExecutor(threads) if threads > 1 else nullcontext() as pool,
    ):
        # Store reads stay on this thread, in image order (the readers cache blocks).
        reads = (describe.read(i) for i in images)
        if pool is None:
            computed = map(rows_of, reads)
        else:
            computed = fastest_in_order(pool, rows_of, reads, threads)
        progress = tqdm(computed, total=len(images), desc=agg.name, unit="image")
        writer = None
        for i, rows in zip(images, progress, strict=True):
            if writer is None:
                dim = rows.shape[1]
                group.attrs["dim"] = dim
                kind = stores.RaggedWriter if by_segment else stores.RowWriter
                chunk_rows = stores.rows_per_chunk(4 * dim)
                writer = kind(
                    group, "descriptors", (dim,), dtype, chunk_rows, stores.FAST_COMPRESSORS
                )
            writer.append(rows, f"descriptors of {dataset.paths[i]}")
        writer.close()


# Images timed each way per round, and at most so many rounds, before fastest_in_order
# settles on one; it settles after any round where one way is CLEAR_MARGIN times faster.
PROBE_IMAGES, PROBE_ROUNDS, CLEAR_MARGIN = 16, 3, 1.5


def fastest_in_order(
    pool: Executor,
    function: Callable,
    items: Iterable,
    workers: int,
    probe: int = PROBE_IMAGES,
    rounds: int = PROBE_ROUNDS,
    clock: Callable[[], float] = time.perf_counter,
) -> Iterator:
    """``function(item)`` for each item, in order, computed on the calling thread or on
    ``pool`` (:func:`in_order`), whichever computed its probes faster.

    Which is faster depends on the method and the features, and neither wins by much
    where it wins: arithmetic made of many small numpy calls holds the GIL, so threads
    only take turns (anyloc_vlad on DAISY features: 0.32 ms an image on the calling
    thread, 0.45 on a pool of 2; SegVLAD without PCA 1.29 against 1.55), while a large
    product lets them work at once (SegVLAD with PCA: 1.21 on the pool against 1.40).
    After ``items[0]`` alone (first-call costs: imports, caches), ``probe`` items are
    computed on this thread, ``probe`` on the pool, ``rounds`` times in turn (or until
    one way is :data:`CLEAR_MARGIN` times faster); each way's fastest round decides.
    A round is timed whole, drawing the items (the store reads) and what the caller
    does with each result (the writes) included: the pool's threads contend with those
    for the GIL, and a probe of the computing alone chose the pool where it was slower.
    A wrong choice under a moving load costs at most the difference.
    """
    items = iter(items)
    for first in itertools.islice(items, 1):
        yield function(first)
    ways = {
        "the calling thread": lambda batch: map(function, batch),
        f"{workers} threads": lambda batch: in_order(pool, function, batch, workers),
    }
    best = dict.fromkeys(ways, float("inf"))
    for _ in range(rounds):
        for way, run in ways.items():
            start, count = clock(), 0
            for result in run(itertools.islice(items, probe)):
                count += 1
                yield result
            if count == 0:
                return
            best[way] = min(best[way], (clock() - start) / count)
        if max(best.values()) > CLEAR_MARGIN * min(best.values()):
            break
    way = min(best, key=best.get)
    log.info(
        "computing on %s (probes: %s)",
        way,
        ", ".join(f"{1000 * seconds:.3f} ms an item on {name}" for name, seconds in best.items()),
    )
    if way == "the calling thread":
        yield from map(function, items)
    else:
        yield from in_order(pool, function, items, workers)


def in_order(pool: Executor, function: Callable, items: Iterable, workers: int) -> Iterator:
    """``function(item)`` for each item, run on ``pool``, yielded in order; at most
    ``2 * workers`` submitted ahead of the one yielded (bounded memory), each item
    drawn from ``items`` on the calling thread."""
    pending: deque[Future] = deque()
    for item in items:
        pending.append(pool.submit(function, item))
        if len(pending) >= 2 * workers:
            yield pending.popleft().result()
    while pending:
        yield pending.popleft().result()
