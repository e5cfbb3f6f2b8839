"""The ``features`` rule: dense patch descriptors of every image (a trained model's
own descriptor as a 1 x 1 grid under ``output: descriptor``)."""

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


def compute_features(job: Job) -> None:
    """Dense patch descriptors ``features [n, h, w, D]`` of the job's images, ``batch_size``
    images a model call."""
    params, batch_size = job.params, job.batch_size
    dataset, images = open_shard(job.inputs["images"], job.data_root, job.start, job.stop)
    width, height = params["resolution"]
    store_dtype = np.dtype(params["store_dtype"])
    extract, patch_size = _feature_extractor(params, job.device, width, height, dataset)
    attrs = {**stage_attrs("features", job.record, images), "sources": _sources(params)}
    with stores.atomic_store(job.out, attrs) as group:
        array = None
        batches = [images[i : i + batch_size] for i in range(0, len(images), batch_size)]
        for batch in tqdm(batches, desc="features", unit="batch"):
            grids = extract(batch)
            if array is None:
                h, w, dim = grids.shape[1:]
                array = group.create_array(
                    "features",
                    shape=(len(images), h, w, dim),
                    chunks=(1, h, w, dim),
                    dtype=store_dtype,
                    compressors=stores.CHECKSUM_ONLY,
                )
                stores.set_attrs(
                    group, grid=[h, w], dim=dim, patch_size=patch_size, image_size=[height, width]
                )
            elif grids.shape[1:] != array.shape[1:]:
                raise ValueError(
                    f"{dataset.paths[batch.start]}: feature grid {grids.shape[1:]} differs from "
                    f"the first image's {array.shape[1:]}"
                )
            start_row = batch.start - images.start
            stored = grids.astype(store_dtype)
            stores.check_finite(group, f"features of {dataset.paths[batch.start]}", stored)
            array[start_row : start_row + len(batch)] = stored


def _sources(params: dict) -> dict[str, str]:
    """The model directory or file the entry reads, and its ``checkpoint`` (a trained
    model's weights, or DINOv2's replaced ones), as absolute paths, for the log and the
    store's attributes."""
    sources = resolved_sources(params)
    if params.get("checkpoint"):
        sources["checkpoint"] = str(Path(params["checkpoint"]).expanduser().resolve())
        log.info("reads checkpoint %s", sources["checkpoint"])
    return sources


def _feature_extractor(params: dict, device: str, width: int, height: int, dataset):
    """``(image indices -> float32 [B, h, w, D], patch size)`` for the configured
    backbone, reading ``dataset``'s images.

    A kind without a loader (``backbone: import``) reads the authors' published HDF5
    features instead of running a model (``<image file name>/ift_dino``).
    """
    kind = model_kind("features", params)
    if kind.reads_file:
        from vprflow.core.arrays import l2_normalize
        from vprflow.data.published import read_features_h5

        def read(indices):
            grids = np.stack(
                [read_features_h5(params["file"], Path(dataset.paths[i]).name) for i in indices]
            )
            return l2_normalize(grids) if params["normalize"] else grids

        return read, params["patch_size"]
    backbone = load_model("features", params, device)

    turn = params["exif_orientation"]  # the method's reader's (plan._exif_orientation)

    def run(indices):
        pixels = np.stack(
            [
                resize_image(dataset.read_image(i, turn), width, height, params["resize"])
                for i in indices
            ]
        )
        return backbone.features(pixels)

    return run, backbone.patch_size
