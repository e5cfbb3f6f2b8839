"""The ``features`` rule: dense patch descriptors of every image (a trained model's
own descriptor as a 1 x 1 grid under ``output: descriptor``)."""

from __future__ import annotations

import logging
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np
from tqdm import tqdm

from vprflow.core import reuse, stores
from vprflow.core.arrays import l2_normalize
from vprflow.core.lazy import lazy_import
from vprflow.data.images import image_size, resize_image
from vprflow.data.published import read_features_h5
from vprflow.models.kinds import OWN_SIZE, model_kind
from vprflow.models.loaders import load_model
from vprflow.stages.base import Job, resolved_sources, stage_attrs
from vprflow.stages.readers import open_shard, reusable_results

devices = lazy_import("vprflow.core.devices")
torch = lazy_import("torch")

log = logging.getLogger("vprflow")

# ``batch_size: auto`` off a GPU: one image a call, as before. On the CPU a batch gives
# each image the same features, bit for bit (tests/models/test_vit.py), and was no faster: one
# image's 1,500 tokens already fill the matrix products (DINOv2 ViT-S/14 at 640 x 480 on
# 2 busy cores, best of 2 rounds: 7.9 s an image alone, 9.0 in pairs, 8.7 in fours).
CPU_BATCH_SIZE = 1


def compute_features(job: Job) -> None:
    """Dense patch descriptors ``features [n, h, w, D]`` of the job's images, ``batch_size``
    images a model call (``auto``: :func:`_batch_sizes`). Under ``resolution: own`` each
    image keeps its own size, and a batch is cut where the size changes.

    Host threads keep the model busy: ``job.threads`` of them read and resize the
    images of the next batches while it computes, and the store's writer thread
    (:class:`~vprflow.core.stores.RowWriter`) writes the features of the last.

    An image whose features a finished features store of the same settings holds
    (:mod:`vprflow.core.reuse`: the same image bytes, under any name, in any dataset) is
    not computed: its chunk file, one image's features, is hard-linked from there, so
    the store is the same file for file and the bytes are stored once; the model is
    loaded only if an image is left to compute. The log says how many of each."""
    params = job.params
    dataset, images = open_shard(job.inputs["images"], job.data_root, job.start, job.stop)
    own = params["resolution"] == OWN_SIZE
    size = None if own else tuple(params["resolution"])
    image_hw = _own_size(params, dataset) if own else [size[1], size[0]]
    store_dtype = np.dtype(params["store_dtype"])
    attrs = {**stage_attrs("features", job.record, images), "sources": _sources(params)}
    sources = reusable_results(job, dataset, images)
    with stores.atomic_store(job.out, attrs) as group:
        writer, reused = None, set()
        if sources:
            source = next(iter(sources.values())).group
            writer = _writer(
                group,
                source["features"].shape[1:],
                store_dtype,
                image_hw,
                source.attrs["patch_size"],
            )
            reused = _link(writer.array, sources, images.start)
        left = [index for index in images if index not in reused]
        if left:
            writer = _compute(job, dataset, size, left, (group, writer, image_hw, images.start))
        if writer is not None:
            writer.skip(len(images) - writer.written - writer.buffered)  # the last reused
            writer.close()
    log.info(reuse.IMAGES_LINE, len(left), len(reused))


def _writer(group, grid_shape, store_dtype, image_hw, patch_size) -> stores.RowWriter:
    """The store's ``features`` array, one image a chunk, and its grid attributes."""
    h, w, dim = (int(n) for n in grid_shape)
    writer = stores.RowWriter(
        group,
        "features",
        (h, w, dim),
        store_dtype,
        1,
        stores.CHECKSUM_ONLY,
        chunk_key_encoding=stores.FLAT_CHUNK_KEYS,
    )
    stores.set_attrs(group, grid=[h, w], dim=dim, patch_size=patch_size, image_size=image_hw)
    return writer


def _link(array, sources: dict[int, reuse.Source], first: int) -> set[int]:
    """Link each source's chunk file in as image ``index``'s (row ``index - first``);
    the indices linked (a source of another shape or dtype, or that fails its checks,
    is left to compute)."""
    chunk_bytes = array.dtype.itemsize * int(np.prod(array.shape[1:]))
    linked = set()
    for index, source in sources.items():
        theirs = source.group["features"]
        if theirs.shape[1:] != array.shape[1:] or theirs.dtype != array.dtype:
            continue
        if (
            theirs.chunks != (1, *theirs.shape[1:])
            or theirs.raw.compressors != stores.CHECKSUM_ONLY
        ):
            continue
        mine = reuse.chunk_file(array, index - first)
        if reuse.link_chunk(reuse.chunk_file(theirs.raw, source.index), mine, chunk_bytes):
            linked.add(index)
    return linked


def _compute(job: Job, dataset, size, left: list[int], into: tuple) -> stores.RowWriter:
    """Compute the features of images ``left`` (in order) into the store: ``into`` is
    ``(group, writer or None, image_hw, the job's first image)``; the writer."""
    group, writer, image_hw, first = into
    params = job.params
    store_dtype = np.dtype(params["store_dtype"])
    read, extract, patch_size, device = _feature_extractor(params, job.device, size, dataset)
    sizes = _batch_sizes(job.batch_size, device, extract)
    with (
        ThreadPoolExecutor(max(1, job.threads), thread_name_prefix="read") as pool,
        tqdm(total=len(left), desc="features", unit="image") as progress,
    ):
        ahead = _ReadAhead(pool, read, left)
        done = 0
        try:
            while done < len(left):
                grids, count = sizes.run(ahead, len(left) - done)
                if writer is None:
                    writer = _writer(group, grids.shape[1:], store_dtype, image_hw, patch_size)
                elif grids.shape[1:] != writer.array.shape[1:]:
                    raise ValueError(
                        f"{dataset.paths[left[done]]}: feature grid {grids.shape[1:]} differs "
                        f"from the first image's {writer.array.shape[1:]}"
                    )
                for low, high in _runs(left, done, done + count):
                    # Rows of images reused lie between runs: their files are in place.
                    writer.skip(left[low] - first - writer.written - writer.buffered)
                    writer.append(
                        grids[low - done : high - done], f"features of {dataset.paths[left[low]]}"
                    )
                done += count
                progress.update(count)
        finally:
            ahead.cancel()
    return writer


def _runs(indices: list[int], start: int, stop: int) -> list[tuple[int, int]]:
    """``indices[start:stop]`` cut into runs of consecutive values, as position ranges."""
    runs, low = [], start
    for at in range(start + 1, stop):
        if indices[at] != indices[at - 1] + 1:
            runs.append((low, at))
            low = at
    return [*runs, (low, stop)] if stop > start else runs


class _ReadAhead:
    """Images read and resized on ``pool``'s threads in order, a window of them ahead
    of the batch the model computes: :meth:`take` waits for the next ``count`` (stacked
    ``[count, H, W, 3]``) and keeps ``ahead`` more reading."""

    def __init__(self, pool: ThreadPoolExecutor, read, images: list[int]):
        self.pool, self.read = pool, read
        self.queue: deque[Future] = deque()
        self.next = iter(images)

    def _fill(self, count: int) -> None:
        while len(self.queue) < count:
            index = next(self.next, None)
            if index is None:
                return
            self.queue.append(self.pool.submit(self.read, index))

    def take(self, count: int, ahead: int) -> list[np.ndarray]:
        self._fill(count + ahead)
        batch = [self.queue.popleft().result() for _ in range(min(count, len(self.queue)))]
        self._fill(ahead)
        return batch

    def cancel(self) -> None:
        """Drop the reads not started (after an error)."""
        for future in self.queue:
            future.cancel()


class _BatchSizes:
    """Images a model call: a fixed ``batch_size``, or (``auto`` on a CUDA device) one
    image first, whose activations' peak memory sets the batch size for the rest
    (:func:`vprflow.core.devices.batch_for_memory`), halved when a batch runs out of
    memory nonetheless."""

    def __init__(self, extract, size: int | None, device=None):
        self.extract, self.size, self.device = extract, size, device

    def run(self, ahead: _ReadAhead, left: int) -> tuple[np.ndarray, int]:
        """Features of the next batch (at most ``left`` images) and its length."""
        if self.size is None:
            return self._probe(np.stack(ahead.take(1, 1))), 1
        images = ahead.take(min(self.size, left), self.size)
        grids = [self._extract(np.stack(run)) for run in equal_size_runs(images)]
        return (grids[0] if len(grids) == 1 else np.concatenate(grids)), len(images)

    def _probe(self, pixels: np.ndarray) -> np.ndarray:
        # The peak since here is this image's: the stage's reported peak CUDA memory
        # (the runner's resources line) counts from here on, the weights included.
        torch.cuda.synchronize(self.device)
        torch.cuda.reset_peak_memory_stats(self.device)
        before = torch.cuda.memory_allocated(self.device)
        grids = self.extract(pixels)
        per_image = torch.cuda.max_memory_allocated(self.device) - before
        self.size = devices.batch_for_memory(devices.free_memory(self.device), per_image)
        log.info(
            "batch_size auto: %d images a batch (%.0f MiB of activations an image)",
            self.size,
            per_image / 2**20,
        )
        return grids

    def _extract(self, pixels: np.ndarray) -> np.ndarray:
        if self.device is None:
            return self.extract(pixels)
        try:
            return self.extract(pixels)
        except torch.cuda.OutOfMemoryError:
            if len(pixels) == 1:
                raise
        # Out of the except clause, so that the error's frames release their tensors.
        torch.cuda.empty_cache()
        self.size = max(1, len(pixels) // 2)
        log.info("batch_size auto: out of memory, %d images a batch", self.size)
        parts = [pixels[i : i + self.size] for i in range(0, len(pixels), self.size)]
        return np.concatenate([self._extract(part) for part in parts])


def equal_size_runs(images: list[np.ndarray]) -> list[list[np.ndarray]]:
    """``images`` in order, cut into runs of one shape: what one model call can stack."""
    runs: list[list[np.ndarray]] = []
    for image in images:
        if runs and runs[-1][-1].shape == image.shape:
            runs[-1].append(image)
        else:
            runs.append([image])
    return runs


def _own_size(params: dict, dataset) -> list[int] | None:
    """``[height, width]`` shared by every image of the dataset as the features stage
    reads it (its ``exif_orientation``), for the store's ``image_size``; ``None`` where
    sizes differ, which only a model's own descriptor (``output: descriptor``) allows:
    a dense map is stacked by the stages after it, so an image of another size is
    refused, naming it."""
    turn = params["exif_orientation"]
    if turn == dataset.exif_orientation:  # the images stage's sizes, read as here
        sizes = np.asarray(dataset.group["image_sizes"][...])
    else:
        sizes = np.array([image_size(path, turn)[::-1] for path in dataset.paths])
    wrong = np.flatnonzero((sizes != sizes[0]).any(axis=1))
    if not len(wrong):
        return [int(v) for v in sizes[0]]
    if params.get("output", "features") == "descriptor":
        return None
    (height, width), (h, w) = sizes[0], sizes[wrong[0]]
    more = f" (and {len(wrong) - 1} more images differ)" if len(wrong) > 1 else ""
    raise ValueError(
        f"{dataset.paths[wrong[0]]} is {w} x {h}, but {dataset.paths[0]} is {width} x "
        f"{height}{more}: backbone {params['backbone']!r} reads each image at its own size "
        f"(resolution: {OWN_SIZE}), and its dense map (output: features) needs one size "
        "for every image, as the stages after it stack the maps; give the backbone entry "
        "a `resolution: [width, height]` (or `dataset`) to resize them all"
    )


def _batch_sizes(batch_size, device, extract) -> _BatchSizes:
    """The batch sizes of ``batch_size`` (a backbone entry's): a whole number, or
    ``auto``: :data:`CPU_BATCH_SIZE` unless the model runs on a CUDA ``device``."""
    if batch_size == "auto":
        if device is None or device.type != "cuda":
            return _BatchSizes(extract, CPU_BATCH_SIZE)
        return _BatchSizes(extract, None, device)
    if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
        raise ValueError(f"batch_size must be a whole number >= 1 or 'auto', got {batch_size!r}")
    return _BatchSizes(extract, batch_size)


def _sources(params: dict) -> dict[str, str]:
    """The model directory or file the entry reads, and its ``checkpoint`` (a trained
    model's weights, or DINOv2's replaced ones), as absolute paths, for the log and the
    store's attributes."""
    sources = resolved_sources(params)
    if params.get("checkpoint"):
        sources["checkpoint"] = str(Path(params["checkpoint"]).expanduser().resolve())
        log.info("reads checkpoint %s", sources["checkpoint"])
    return sources


def _feature_extractor(params: dict, device: str, size: tuple[int, int] | None, dataset):
    """``(read, extract, patch size, torch device or None)`` for the configured backbone:
    ``read(image index)`` gives what ``extract`` takes a stack of (an image resized to
    ``size``, ``(width, height)``, or at its own size where ``size`` is None; float32
    in [0, 1]), ``extract`` float32 ``[B, h, w, D]``; the device is where the model
    runs (None: a model without one).

    A kind without a loader (``backbone: import``) reads the authors' published HDF5
    features instead of running a model (``<image file name>/ift_dino``).
    """
    kind = model_kind("features", params)
    if kind.reads_file:

        def read_grid(index):
            return read_features_h5(params["file"], Path(dataset.paths[index]).name)

        def normalize(grids):
            return l2_normalize(grids) if params["normalize"] else grids

        return read_grid, normalize, params["patch_size"], None
    backbone = load_model("features", params, device)

    turn = params["exif_orientation"]  # the method's reader's (plan._exif_orientation)

    def read_image(index):
        image = dataset.read_image(index, turn)
        return image if size is None else resize_image(image, *size, params["resize"])

    return read_image, backbone.features, backbone.patch_size, getattr(backbone, "device", None)
