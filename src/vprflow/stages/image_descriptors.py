"""How the descriptors and pca stages compute an aggregator's descriptor of one image:
the aggregator entry's ``compute`` over the image's patch grid and what its ``needs``
give, read from their stores, for every aggregator alike."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from vprflow.aggregation.aggregators import Aggregator
from vprflow.core import stores
from vprflow.stages.readers import FeatureReader, MaskReader, read_centres


@dataclass(frozen=True)
class ImageDescriptor:
    """One image's descriptor in two steps: ``read(index)`` -> a tuple of its inputs
    (store reads: one thread, images in order), ``compute(*inputs)`` -> descriptor
    (arithmetic only: safe on several images at once). Calling it does both."""

    read: Callable[[int], tuple]
    compute: Callable[..., np.ndarray]

    def __call__(self, index: int) -> np.ndarray:
        return self.compute(*self.read(index))


def image_descriptor(agg: Aggregator, options: dict, inputs: dict[str, str]) -> ImageDescriptor:
    """``agg``'s descriptor of each image with ``options``, from the input stores
    ``inputs``: its ``compute`` over the image's patch grid, given what its ``needs``
    name (``centres`` of the vocabulary; ``masks``, ``image_size`` and ``patch_size``
    of the segments)."""
    features = stores.open_store(inputs["features"])
    read_features = FeatureReader(features)
    if agg.reads == "descriptor":
        grid = tuple(features["features"].shape[1:3])
        if grid != (1, 1):
            # The plan pairs a descriptor reader with descriptor outputs only; a store
            # made otherwise (an older plan, a hand-made store) is named, not averaged.
            raise ValueError(
                f"features store {inputs['features']} holds a {grid[0]} x {grid[1]} grid "
                f"per image, not a trained model's descriptor (1 x 1): aggregator "
                f"{agg.name!r} reads a trained backbone entry with output: descriptor"
            )
    fixed = {}
    if "vocabulary" in agg.needs:
        fixed["centres"] = read_centres(inputs["vocabulary"])
    compute, settings = agg.compute, options
    if "segments" not in agg.needs:
        return ImageDescriptor(
            lambda index: (read_features(index),), lambda grid: compute(grid, settings, **fixed)
        )
    read_masks = MaskReader(stores.open_store(inputs["segments"]))
    height, width = features.attrs["image_size"]
    fixed |= {"image_size": (height, width), "patch_size": int(features.attrs["patch_size"])}
    return ImageDescriptor(
        lambda index: (read_features(index), read_masks(index)),
        lambda grid, masks: compute(grid, settings, masks=masks, **fixed),
    )
