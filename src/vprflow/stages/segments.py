"""The ``segments`` rule: bit-packed segment masks of every image."""

from __future__ import annotations

import functools
import logging
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
from tqdm import tqdm

from vprflow.core import reuse, stores
from vprflow.data.images import resize_image
from vprflow.data.published import read_masks_h5
from vprflow.models.kinds import model_kind
from vprflow.models.loaders import load_model
from vprflow.stages.base import Job, resolved_sources, stage_attrs
from vprflow.stages.readers import open_shard, reusable_results

log = logging.getLogger("vprflow")
# Masks a chunk of the ragged ``masks`` array: many images' each.
CHUNK_ROWS = 256


def compute_segments(job: Job) -> None:
    """Bit-packed masks per image of the job's images at the segmentation resolution
    (ragged ``masks``).

    ``batch_size`` images share one image-encoder pass (SAM kinds; others run one by one).
    While a batch is segmented, a host thread reads and resizes the next one and another
    packs and writes the last one's masks, so the segmenter's device never waits on them.

    An image whose masks a finished segments store of the same settings holds
    (:mod:`vprflow.core.reuse`: the same bytes, under any name, in any dataset) is not
    segmented: its packed rows are copied from there (checked as every store read is;
    one that fails is segmented instead). The store is the same either way. Its chunks
    hold many images' rows, so rows cannot be linked one by one; a chunk whose file is
    byte for byte one of another store's at the same index (the same images at the same
    rows: shared references, images added at the end) is hard-linked to it
    (:func:`vprflow.core.reuse.link_equal_chunks`), so such masks are on disk once. The
    segmenter is loaded only if an image is left to segment; the log says how many of
    each."""
    params = job.params
    dataset, images = open_shard(job.inputs["images"], job.data_root, job.start, job.stop)
    attrs = {**stage_attrs("segments", job.record, images), "sources": resolved_sources(params)}
    sources = reusable_results(job, dataset, images)
    left = [index for index in images if index not in sources]
    masker = functools.cache(lambda: _mask_source(params, job.device, dataset))
    computed = _segmented(*masker(), left, job.batch_size) if left else iter(())
    readers: dict[Path, stores.RaggedReader] = {}
    reused = 0
    with stores.atomic_store(job.out, attrs) as group, ThreadPoolExecutor(1) as packing:
        writer, shape, written = None, None, None
        for i in images:
            rows = _reused_rows(sources.get(i), readers)
            if rows is not None:
                reused += 1
                packed, size = rows
            else:
                if i in sources:  # its stored rows failed their checks
                    read, segment = masker()
                    masks = segment(read([i]))[0]
                else:
                    index, masks = next(computed)
                    assert index == i, (index, i)
                packed, size = None, masks.shape[1:]
                if len(masks) == 0:
                    log.warning("%s: the segmenter returned no masks", dataset.paths[i])
            if shape is None:
                shape = size
                stores.set_attrs(group, mask_height=shape[0], mask_width=shape[1])
                writer = stores.RaggedWriter(
                    group, "masks", ((shape[0] * shape[1] + 7) // 8,), np.uint8, CHUNK_ROWS
                )
            elif size != shape:
                raise ValueError(
                    f"{dataset.paths[i]}: masks of size {size} differ from the "
                    f"first image's {shape}"
                )
            if written is not None:
                written.result()  # in order, one image ahead at most; re-raises its error
            if packed is None:
                written = packing.submit(_append_packed, writer, masks)
            else:
                written = packing.submit(writer.append, packed)
        if written is not None:
            written.result()
        writer.close()
        if reused and job.start is None:  # a shard's chunks are linked by its gather
            array = stores.array_directory(writer.array)
            reuse.link_equal_chunks(array, job.record, Path(job.out).parent)
    log.info(reuse.IMAGES_LINE, len(images) - reused, reused)


def _reused_rows(source: reuse.Source | None, readers: dict) -> tuple[np.ndarray, tuple] | None:
    """``(packed rows, (mask height, width))`` of ``source``'s image, or None: no source,
    or its rows fail their checks (a warning; the image is segmented instead)."""
    if source is None:
        return None
    group = source.group
    if group.path not in readers:
        readers[group.path] = stores.RaggedReader(group, "masks")
    try:
        rows = readers[group.path](source.index)
    except stores.StoreCorruptError as error:
        log.warning("segmenting again an image whose stored masks fail their checks: %s", error)
        return None
    return rows, (int(group.attrs["mask_height"]), int(group.attrs["mask_width"]))


def _append_packed(writer: stores.RaggedWriter, masks: np.ndarray) -> None:
    writer.append(stores.pack_masks(masks))


def _segmented(read, segment, images, batch_size: int):
    """``(index, masks)`` of each image of ``images`` (indices, in order):
    ``segment(read(indices))`` on lists of up to ``batch_size`` of them, the next batch
    read on a host thread meanwhile, with a progress bar over images."""
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    batches = [
        list(images[first : first + batch_size]) for first in range(0, len(images), batch_size)
    ]
    with (
        tqdm(total=len(images), desc="segments", unit="image") as progress,
        ThreadPoolExecutor(1) as reading,
    ):
        upcoming = reading.submit(read, batches[0]) if batches else None
        for number, batch in enumerate(batches):
            inputs = upcoming.result()
            if number + 1 < len(batches):
                upcoming = reading.submit(read, batches[number + 1])
            yield from zip(batch, segment(inputs), strict=True)
            progress.update(len(batch))


def _mask_source(params: dict, device: str, dataset):
    """``(read, segment)`` for the configured segmenter: ``read([image index, ...])`` ->
    what ``segment`` takes, ``segment(...)`` -> ``[bool [S, Hm, Wm], ...]``, reading
    ``dataset``'s images.

    ``segmenter: import`` reads the authors' published HDF5 masks
    (``<image file name>/masks/<j>/segmentation``) at their own resolution. Segmenters
    with ``masks_batch`` (SAM kinds) take a list of images in one call.
    """
    kind = model_kind("segments", params)
    if kind.reads_file:

        def published(indices):
            return [read_masks_h5(params["file"], Path(dataset.paths[i]).name) for i in indices]

        return published, lambda masks: masks
    segmenter = load_model("segments", params, device)
    width, height = params["resolution"]

    turn = params["exif_orientation"]  # as the method's features (plan._exif_orientation)

    def images(indices):
        return [
            resize_image(dataset.read_image(i, turn), width, height, params["resize"])
            for i in indices
        ]

    if hasattr(segmenter, "masks_batch"):
        return images, segmenter.masks_batch
    return images, lambda batch: [segmenter.masks(image) for image in batch]
