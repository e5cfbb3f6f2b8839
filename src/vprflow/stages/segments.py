"""The ``segments`` rule: bit-packed segment masks of every image."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from tqdm import tqdm

from vprflow.core import stores
from vprflow.data.images import resize_image
from vprflow.models.kinds import model_kind
from vprflow.models.loaders import load_model
from vprflow.stages.base import Job, resolved_sources, stage_attrs
from vprflow.stages.readers import open_shard

log = logging.getLogger("vprflow")


def compute_segments(job: Job) -> None:
    """Bit-packed masks per image of the job's images at the segmentation resolution
    (ragged ``masks``).

    ``batch_size`` images share one image-encoder pass (SAM kinds; others run one by one).
    """
    params = job.params
    dataset, images = open_shard(job.inputs["images"], job.data_root, job.start, job.stop)
    segment = _mask_source(params, job.device, dataset)
    attrs = {**stage_attrs("segments", job.record, images), "sources": resolved_sources(params)}
    with stores.atomic_store(job.out, attrs) as group:
        writer, shape = None, None
        for i, masks in _segmented(segment, images, job.batch_size):
            if shape is None:
                shape = masks.shape[1:]
                stores.set_attrs(group, mask_height=shape[0], mask_width=shape[1])
                writer = stores.RaggedWriter(
                    group, "masks", ((shape[0] * shape[1] + 7) // 8,), np.uint8, chunk_rows=256
                )
            elif masks.shape[1:] != shape:
                raise ValueError(
                    f"{dataset.paths[i]}: masks of size {masks.shape[1:]} differ from the "
                    f"first image's {shape}"
                )
            if len(masks) == 0:
                log.warning("%s: the segmenter returned no masks", dataset.paths[i])
            writer.append(stores.pack_masks(masks))
        writer.close()


def _segmented(segment, images, batch_size: int):
    """``(index, masks)`` of each image in order, ``segment`` called on lists of up to
    ``batch_size`` image indices, with a progress bar over images."""
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    with tqdm(total=len(images), desc="segments", unit="image") as progress:
        for first in range(0, len(images), batch_size):
            batch = images[first : first + batch_size]
            yield from zip(batch, segment(list(batch)), strict=True)
            progress.update(len(batch))


def _mask_source(params: dict, device: str, dataset):
    """``[image index, ...] -> [bool [S, Hm, Wm], ...]`` for the configured segmenter,
    reading ``dataset``'s images.

    ``segmenter: import`` reads the authors' published HDF5 masks
    (``<image file name>/masks/<j>/segmentation``) at their own resolution. Segmenters
    with ``masks_batch`` (SAM kinds) take a list of images in one call.
    """
    kind = model_kind("segments", params)
    if kind.reads_file:
        from vprflow.data.published import read_masks_h5

        return lambda indices: [
            read_masks_h5(params["file"], Path(dataset.paths[i]).name) for i in indices
        ]
    segmenter = load_model("segments", params, device)
    width, height = params["resolution"]

    turn = params["exif_orientation"]  # as the method's features (plan._exif_orientation)

    def images(indices):
        return [
            resize_image(dataset.read_image(i, turn), width, height, params["resize"])
            for i in indices
        ]

    if hasattr(segmenter, "masks_batch"):
        return lambda indices: segmenter.masks_batch(images(indices))
    return lambda indices: [segmenter.masks(image) for image in images(indices)]
