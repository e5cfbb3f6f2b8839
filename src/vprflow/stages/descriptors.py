"""The ``descriptors`` rule: each method's descriptors of every image.

What a method computes per image is its registry entry's ``image_descriptor``
(:mod:`vprflow.core.registry`), one of the functions at the end of this module: its
own, or :func:`grid_descriptor`, which runs the entry's ``compute`` (plain math over
the patch grid) for an aggregator that reads nothing but the features.
"""

from __future__ import annotations

import itertools
import logging
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass

import numpy as np
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from vprflow.core import stores
from vprflow.core.arrays import l2_normalize
from vprflow.core.registry import aggregator
from vprflow.stages.base import Job, stage_attrs
from vprflow.stages.dataset import Dataset
from vprflow.stages.features import FeatureReader
from vprflow.stages.pca import read_pca
from vprflow.stages.segments import MaskReader
from vprflow.stages.vocabulary import read_centres

log = logging.getLogger("vprflow")


def compute_descriptors(job: Job) -> None:
    """Per-image descriptors of one method over the job's images, as its registry entry
    computes them.

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
    describe = agg.descriptor_function(params, inputs)
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


# ------------------------------------------------------------------ per-image functions
# Each takes the method's options and the input store paths and returns an
# ImageDescriptor: ``read(index)`` -> the image's inputs, ``compute(*inputs)`` ->
# ``[dim]``, or ``[S, dim]`` for segment aggregators.


@dataclass(frozen=True)
class ImageDescriptor:
    """One image's descriptor in two steps: ``read(index)`` -> a tuple of its inputs
    (store reads: one thread, images in order), ``compute(*inputs)`` -> descriptor
    (arithmetic only: safe on several images at once). Calling it does both."""

    read: Callable[[int], tuple]
    compute: Callable[..., np.ndarray]

    def __call__(self, index: int) -> np.ndarray:
        return self.compute(*self.read(index))


def vlad_input(grid: np.ndarray, options: dict) -> np.ndarray:
    """Patches as VLAD sees them: L2-normalised per patch unless the method says not
    (AnyLoc's VLAD ``norm_descs=True``; stored float16 features are only nearly unit)."""
    return l2_normalize(grid) if options["normalize_descriptors"] else grid


def segvlad_descriptors(options: dict, inputs: dict[str, str]):
    """SegVLAD: one VLAD vector per segment neighbourhood of ``options["order"]``
    (docs/methods.md §5), ``[S, K * D]``."""
    from vprflow.aggregation.segvlad import image_segvlad

    features = stores.open_store(inputs["features"])
    read_features = FeatureReader(features)
    read_masks = MaskReader(stores.open_store(inputs["segments"]))
    centres = read_centres(inputs["vocabulary"])
    height, width = features.attrs["image_size"]
    patch_size = int(features.attrs["patch_size"])

    def compute(features: np.ndarray, masks: np.ndarray) -> np.ndarray:
        return image_segvlad(
            vlad_input(features, options),
            masks,
            centres,
            (height, width),
            patch_size,
            options["order"],
            crop_aligned=options["mask_to_patch"] == "crop_aligned",
            small_graph=options["small_graph"],
        )

    return ImageDescriptor(lambda index: (read_features(index), read_masks(index)), compute)


def anyloc_vlad_descriptor(options: dict, inputs: dict[str, str]):
    """AnyLoc VLAD of the whole patch grid (docs/methods.md §4), ``[K * D]``."""
    from vprflow.aggregation.vlad import vlad

    read_features = FeatureReader(stores.open_store(inputs["features"]))
    centres = read_centres(inputs["vocabulary"])

    def compute(grid: np.ndarray) -> np.ndarray:
        grid = vlad_input(grid, options)
        return vlad(grid.reshape(-1, grid.shape[-1]), centres)

    return ImageDescriptor(lambda index: (read_features(index),), compute)


def snsm_descriptor(options: dict, inputs: dict[str, str]):
    """SNSM support-map descriptor (docs/methods.md §6)."""
    from vprflow.aggregation.snsm import snsm_descriptor as snsm

    read_features = FeatureReader(stores.open_store(inputs["features"]))
    keys = ("upscale", "window", "neighbourhood", "similarity", "normalization")
    settings = {k: options[k] for k in keys}
    return ImageDescriptor(
        lambda index: (read_features(index),), lambda grid: snsm(grid, **settings)
    )


def pooled_descriptor(options: dict, inputs: dict[str, str]):
    """GeM / average / max pooling of the channel-normalised tokens (docs/methods.md §7):
    the SNSM authors pool tokens normalised like SNSM's own input."""
    from vprflow.aggregation import pooling
    from vprflow.aggregation.snsm import normalize_tokens

    read_features = FeatureReader(stores.open_store(inputs["features"]))
    pool = {
        "gem": lambda tokens: pooling.gem(tokens, p=options["p"]),
        "average": pooling.average_pool,
        "max": pooling.max_pool,
    }[options["aggregator"]]
    return ImageDescriptor(
        lambda index: (read_features(index),),
        lambda grid: pool(normalize_tokens(grid, options["normalization"])),
    )


def segment_gem_descriptors(options: dict, inputs: dict[str, str]):
    """Per-segment GeM: each segment's patches (the published mask-to-patch mapping,
    no neighbourhood) GeM-pooled after the pooling section's token normalisation, each
    row L2-normalised for the segment search, ``[S, D]``. SegVLAD's segment path with
    the simplest aggregation: a baseline for what VLAD and neighbourhoods add."""
    from vprflow.aggregation.pooling import segment_gem
    from vprflow.aggregation.segvlad import mask_patch_membership
    from vprflow.aggregation.snsm import normalize_tokens

    features = stores.open_store(inputs["features"])
    read_features = FeatureReader(features)
    read_masks = MaskReader(stores.open_store(inputs["segments"]))
    height, width = features.attrs["image_size"]
    patch_size = int(features.attrs["patch_size"])

    def compute(grid: np.ndarray, masks: np.ndarray) -> np.ndarray:
        h, w, _ = grid.shape
        membership = mask_patch_membership(masks, (height, width), (h, w), patch_size)
        tokens = normalize_tokens(grid, options["normalization"])
        pooled = segment_gem(tokens, membership, options["p"]).astype(np.float64)
        return l2_normalize(pooled).astype(np.float32)

    return ImageDescriptor(lambda index: (read_features(index), read_masks(index)), compute)


def grid_descriptor(options: dict, inputs: dict[str, str], compute: Callable[..., np.ndarray]):
    """A global aggregator's ``compute`` function (its registry entry's
    ``"module:function"``, resolved by :meth:`~vprflow.core.registry.Aggregator.
    descriptor_function`) of the image's patch grid ``[h, w, D]``, the method's options
    as keyword arguments, ``[dim]``: the per-image function of every aggregator that
    reads nothing but the features."""
    settings = {k: v for k, v in options.items() if k != "aggregator"}
    read_features = FeatureReader(stores.open_store(inputs["features"]))
    return ImageDescriptor(
        lambda index: (read_features(index),), lambda grid: compute(grid, **settings)
    )


def model_descriptor(options: dict, inputs: dict[str, str]):
    """A trained model's own descriptor (docs/methods.md, "Trained models"): the 1 x 1
    grid its backbone entry stores under ``output: descriptor``, ``[D]``, L2-normalised
    again in float64 (the models normalise it; a float16 store rounds the norm)."""
    features = stores.open_store(inputs["features"])
    read_features = FeatureReader(features)
    grid = tuple(features["features"].shape[1:3])
    if grid != (1, 1):
        # The plan pairs this aggregator with descriptor outputs only; a store made
        # otherwise (an older plan, a hand-made store) is named, not averaged.
        raise ValueError(
            f"features store {inputs['features']} holds a {grid[0]} x {grid[1]} grid per "
            "image, not a trained model's descriptor (1 x 1): aggregator 'model' reads a "
            "trained backbone entry with output: descriptor"
        )

    def compute(grid: np.ndarray) -> np.ndarray:
        return l2_normalize(grid.reshape(-1).astype(np.float64)).astype(np.float32)

    return ImageDescriptor(lambda index: (read_features(index),), compute)
