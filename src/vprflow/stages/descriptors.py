"""The ``descriptors`` rule: each method's descriptors of every image.

What a method computes per image is its registry entry's ``image_descriptor``
(:mod:`vprflow.registry`), one of the functions at the end of this module.
"""

from __future__ import annotations

import numpy as np
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from vprflow import stores
from vprflow.arrays import l2_normalize
from vprflow.registry import aggregator
from vprflow.stages.base import shard_range, stage_attrs
from vprflow.stages.dataset import Dataset
from vprflow.stages.features import FeatureReader
from vprflow.stages.pca import read_pca
from vprflow.stages.segments import MaskReader
from vprflow.stages.vocabulary import read_centres


def compute_descriptors(
    inputs: dict[str, str],
    params: dict,
    out: str,
    start: int | None = None,
    stop: int | None = None,
) -> None:
    """Per-image descriptors of one method, as its registry entry computes them.

    Aggregators with ``output="segments"`` write a ragged ``descriptors`` array (one
    row per segment, offsets per image), projected by the ``pca`` input when there is
    one; ``output="global"`` aggregators write ``descriptors [n, dim]``.
    """
    spec = params["params"]
    agg = aggregator(spec["aggregator"])
    dataset = Dataset(inputs["dataset"])
    images = shard_range(dataset.n_images, start, stop)
    describe = agg.descriptor_function(spec, inputs)
    by_segment = agg.output == "segments"
    pca = read_pca(inputs["pca"]) if "pca" in inputs else None
    dtype = np.dtype(spec.get("store_dtype", "float32"))
    attrs = {**stage_attrs("descriptors", params, images), "kind": agg.output}
    # One BLAS thread: per-image products are small, and a second thread costs more
    # than it saves (on a busy machine up to 10x: the pool's threads wait for each
    # other). It also makes the stored values independent of the rule's thread count:
    # OpenBLAS rounds a product differently with a different number of threads.
    with stores.atomic_store(out, attrs) as group, threadpool_limits(limits=1):
        writer = None
        for i in tqdm(images, desc=agg.name, unit="image"):
            rows = describe(i) if by_segment else describe(i)[None]
            if pca is not None:
                rows = pca.transform(rows)
            if writer is None:
                dim = rows.shape[1]
                group.attrs["dim"] = dim
                kind = stores.RaggedWriter if by_segment else stores.RowWriter
                writer = kind(group, "descriptors", (dim,), dtype, stores.rows_per_chunk(4 * dim))
            writer.append(rows, f"descriptors of {dataset.paths[i]}")
        writer.close()


# ------------------------------------------------------------------ per-image functions
# Each takes the method's options and the input store paths and returns
# ``image index -> descriptor`` (``[dim]``, or ``[S, dim]`` for segment aggregators).


def vlad_input(grid: np.ndarray, options: dict) -> np.ndarray:
    """Patches as VLAD sees them: L2-normalised per patch unless the method says not
    (AnyLoc's VLAD ``norm_descs=True``; stored float16 features are only nearly unit)."""
    return l2_normalize(grid) if options["normalize_descriptors"] else grid


def segvlad_descriptors(options: dict, inputs: dict[str, str]):
    """SegVLAD: one VLAD vector per segment neighbourhood of ``options["order"]``
    (docs/methods.md §5), ``[S, K * D]``."""
    from vprflow.segvlad import image_segvlad

    features = stores.open_store(inputs["features"])
    read_features = FeatureReader(features)
    read_masks = MaskReader(stores.open_store(inputs["segments"]))
    centres = read_centres(inputs["vocabulary"])
    height, width = features.attrs["image_size"]
    patch_size = int(features.attrs["patch_size"])

    def describe(index: int) -> np.ndarray:
        return image_segvlad(
            vlad_input(read_features(index), options),
            read_masks(index),
            centres,
            (height, width),
            patch_size,
            options["order"],
            crop_aligned=options["mask_to_patch"] == "crop_aligned",
            small_graph=options["small_graph"],
        )

    return describe


def anyloc_vlad_descriptor(options: dict, inputs: dict[str, str]):
    """AnyLoc VLAD of the whole patch grid (docs/methods.md §4), ``[K * D]``."""
    from vprflow.vlad import vlad

    read_features = FeatureReader(stores.open_store(inputs["features"]))
    centres = read_centres(inputs["vocabulary"])

    def describe(index: int) -> np.ndarray:
        grid = vlad_input(read_features(index), options)
        return vlad(grid.reshape(-1, grid.shape[-1]), centres)

    return describe


def snsm_descriptor(options: dict, inputs: dict[str, str]):
    """SNSM support-map descriptor (docs/methods.md §6)."""
    from vprflow.snsm import snsm_descriptor as snsm

    read_features = FeatureReader(stores.open_store(inputs["features"]))
    keys = ("upscale", "window", "neighbourhood", "similarity", "normalization")
    settings = {k: options[k] for k in keys}
    return lambda index: snsm(read_features(index), **settings)


def pooled_descriptor(options: dict, inputs: dict[str, str]):
    """GeM / average / max pooling of the channel-normalised tokens (docs/methods.md §7):
    the SNSM authors pool tokens normalised like SNSM's own input."""
    from vprflow import pooling
    from vprflow.snsm import normalize_tokens

    read_features = FeatureReader(stores.open_store(inputs["features"]))
    pool = {
        "gem": lambda tokens: pooling.gem(tokens, p=options["p"]),
        "average": pooling.average_pool,
        "max": pooling.max_pool,
    }[options["aggregator"]]
    return lambda index: pool(normalize_tokens(read_features(index), options["normalization"]))
