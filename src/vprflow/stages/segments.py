"""The ``segments`` rule: bit-packed segment masks of every image."""

from __future__ import annotations

import functools
import logging
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from vprflow.core import reuse, stores
from vprflow.core.masks import PACKED, PER_IMAGE
from vprflow.data.images import resize_image
from vprflow.data.published import read_masks_h5
from vprflow.models.kinds import model_kind
from vprflow.models.loaders import load_model
from vprflow.stages.base import Job, resolved_sources, stage_attrs
from vprflow.stages.readers import mask_rows, open_shard, reusable_results

log = logging.getLogger("vprflow")
# Masks a chunk file of the ragged ``masks`` array, packed: many images' each.
CHUNK_ROWS = 256
# Masks a chunk file per_image (vprflow.core.masks): SLIC's ~60 an image in one file,
# SAM's ~100 in two; an image's last file padded with empty rows, a few bytes in zstd.
IMAGE_CHUNK_ROWS = 64
# Rows copied from another store a block where they are read (not linked): small enough
# that the writer's thread compresses one while the next is read (grown map of
# benchmarks/bench_reuse.py), at most about a RowWriter write (WRITE_BYTES).
COPY_BYTES = 4 << 20


def compute_segments(job: Job) -> None:
    """Bit-packed masks per image of the job's images at the segmentation resolution
    (ragged ``masks``).

    ``batch_size`` images share one image-encoder pass (SAM kinds; others run one by one).
    While a batch is segmented, a host thread reads and resizes the next one and another
    packs and writes the last one's masks, so the segmenter's device never waits on them.

    An image whose masks a finished segments store of the same settings holds
    (:mod:`vprflow.core.reuse`: the same bytes, under any name, in any dataset) is not
    segmented: its packed rows come from there, a run of such images at a time, checked
    as every store read is (images whose rows fail are segmented instead). The store is
    the same either way. Where a chunk of theirs lands on a whole chunk of ours its file
    is hard-linked in without being decompressed, so those masks are on disk once:
    per_image (:mod:`vprflow.core.masks`) every reused image's files; packed, where
    many images share a chunk, only where the same images follow rows that end on a
    chunk boundary in both (shared references, images added at the end), and afterwards
    a chunk byte for byte one of another store's at the same index is linked to it
    (:func:`vprflow.core.reuse.link_equal_chunks`). The segmenter is loaded only if an
    image is left to segment; the log says how many of each."""
    params = job.params
    dataset, images = open_shard(job.inputs["images"], job.data_root, job.start, job.stop)
    attrs = {**stage_attrs("segments", job.record, images), "sources": resolved_sources(params)}
    sources = reusable_results(job, dataset, images)
    left = [index for index in images if index not in sources]
    masker = functools.cache(lambda: _mask_source(params, job.device, dataset))
    computed = _segmented(*masker(), left, job.batch_size) if left else iter(())
    layout = params.get("masks_layout", PACKED)
    with stores.atomic_store(job.out, attrs) as group, _Masks(group, dataset, layout) as masks:
        for run in _runs(images, sources):
            if run.source is None:
                for i in run.images:
                    index, segmented = next(computed)
                    assert index == i, (index, i)
                    masks.segmented(i, segmented)
                continue
            for i in masks.copied(run):  # their stored rows failed their checks
                rows = masks.stored(sources[i])
                if rows is not None:
                    masks.packed(i, *rows)
                else:
                    read, segment = masker()
                    masks.segmented(i, segment(read([i]))[0])
        masks.close()
        # per_image: each reused image's files were linked as they were copied.
        if masks.reused and masks.counts is None and job.start is None:
            array = stores.array_directory(masks.writer.array)
            reuse.link_equal_chunks(array, job.record, Path(job.out).parent)
    log.info(reuse.IMAGES_LINE, len(images) - masks.reused, masks.reused)


@dataclass(frozen=True)
class _Run:
    """Consecutive images of a job (``images``, indices into its dataset): segmented
    (``source`` None), or reused from consecutive images of one store, the first of
    them ``source``."""

    images: list[int]
    source: reuse.Source | None


def _runs(images: range, sources: dict[int, reuse.Source]) -> list[_Run]:
    """``images`` cut into :class:`_Run`\\ s."""
    runs: list[_Run] = []
    for i in images:
        source, last = sources.get(i), runs[-1] if runs else None
        if last is not None and (
            (source is None and last.source is None)
            or (
                source is not None
                and last.source is not None
                and source.group is last.source.group
                and source.index == last.source.index + len(last.images)
            )
        ):
            last.images.append(i)
        else:
            runs.append(_Run([i], source))
    return runs


class _Masks:
    """The store's ``masks`` in ``layout`` (:mod:`vprflow.core.masks`), appended in image
    order on one packing thread, one call ahead of the caller at most, the array made at
    the first image's mask size (each next image's checked against it)."""

    def __init__(self, group, dataset, layout: str):
        self.group, self.dataset = group, dataset
        self.chunk_rows = IMAGE_CHUNK_ROWS if layout == PER_IMAGE else CHUNK_ROWS
        # per_image: each image's masks, its rows less their padding (masks_counts).
        self.counts: list[int] | None = [] if layout == PER_IMAGE else None
        self.writer: stores.RaggedWriter | None = None
        self.size: tuple | None = None  # the masks' (height, width)
        self.rows = 0  # rows appended or queued so far
        self.reused = 0
        self._rows: dict[Path, tuple[np.ndarray, np.ndarray]] = {}  # sources' mask_rows
        self._alike: dict[Path, bool] = {}
        self._packing = ThreadPoolExecutor(1, thread_name_prefix="pack-masks")
        self._pending: Future | None = None

    def __enter__(self):
        return self

    def __exit__(self, *error):
        self._packing.shutdown()

    def segmented(self, index: int, masks: np.ndarray) -> None:
        """Append image ``index``'s masks (bool ``[S, Hm, Wm]``), packed on the thread."""
        self._size(index, masks.shape[1:])
        if len(masks) == 0:
            log.warning("%s: the segmenter returned no masks", self.dataset.paths[index])
        padding = self._record(len(masks))
        self._queue(len(masks) + padding, _append_packed, self.writer, masks, padding)

    def packed(self, index: int, rows: np.ndarray, size: tuple) -> None:
        """Append image ``index``'s packed masks ``rows`` of masks of ``size``."""
        self._size(index, size)
        self.reused += 1
        rows = _padded(rows, self._record(len(rows)))
        self._queue(len(rows), self.writer.append, rows)

    def copied(self, run: _Run) -> list[int]:
        """Append the stored rows of ``run``'s images (reused) -> the images left to the
        caller (in order, before any other is appended): from the first whose block of
        rows fails its checks (a warning) to the run's end.

        Blocks of whole images, :data:`COPY_BYTES` of rows, each written (or linked) on
        the threads while the next is read. Where their chunks land on whole chunks of
        ours (:func:`reuse.read_rows`; per_image, always) those are linked, and a
        packed run is one block: what is read is only the rows before its first whole
        chunk and after its last."""
        group = run.source.group
        offsets, counts = self._rows_of(group)
        self._size(run.images[0], _mask_size(group))
        if group.path not in self._alike:
            ours = stores.array_directory(self.writer.array)
            self._alike[group.path] = reuse.same_chunks(ours, group.path / "masks")
        done, end = run.source.index, run.source.index + len(run.images)
        aligned = (self.rows - int(offsets[done])) % self.chunk_rows == 0  # always per_image
        link = self._alike[group.path] and aligned
        block = max(1, COPY_BYTES // self.writer.array.shape[1])  # rows of uint8
        if link and self.counts is None:  # packed: a block's end inside a chunk loses its link
            block = int(offsets[end] - offsets[done])
        while done < end:
            stop = int(np.searchsorted(offsets, offsets[done] + block, "right")) - 1
            stop = min(max(stop, done + 1), end)
            low, high = int(offsets[done]), int(offsets[stop])
            try:
                pieces = reuse.read_rows(group["masks"], low, high, self.rows, link)
            except stores.StoreCorruptError as error:
                log.warning("segmenting images whose stored masks fail their checks: %s", error)
                return run.images[done - run.source.index :]
            lengths = np.diff(offsets[done : stop + 1])
            self._queue(high - low, _append_images, self.writer, pieces, lengths)
            if self.counts is not None:
                self.counts.extend(counts[done:stop].tolist())
            self.reused += stop - done
            done = stop
        return []

    def stored(self, source: reuse.Source) -> tuple[np.ndarray, tuple] | None:
        """``(packed rows, (mask height, width))`` of ``source``'s image alone, or None
        where they fail their checks (a warning; the image is segmented instead). Its
        rows only, so that a damaged chunk costs only the images with rows in it."""
        offsets, counts = self._rows_of(source.group)
        low = int(offsets[source.index])
        high = low + int(counts[source.index])
        try:
            rows = np.asarray(source.group["masks"][low:high])
        except stores.StoreCorruptError as error:
            log.warning("segmenting an image whose stored masks fail their checks: %s", error)
            return None
        return rows, _mask_size(source.group)

    def close(self) -> None:
        """Wait for the last append, then write the offsets (and per_image counts)."""
        self._wait()
        if self.writer is not None:
            self.writer.close()
        if self.counts is not None:
            # Chunks of a fixed length, so that a gathered store's are the same files.
            counts = np.asarray(self.counts, np.int64)
            stores.write_array(self.group, "masks_counts", counts, chunks=(1 << 16,))

    def _rows_of(self, group: stores.CheckedGroup) -> tuple[np.ndarray, np.ndarray]:
        if group.path not in self._rows:
            self._rows[group.path] = mask_rows(group)
        return self._rows[group.path]

    def _record(self, count: int) -> int:
        """Record an image of ``count`` masks -> the empty rows after them: per_image, to
        the end of its last file; packed, none."""
        if self.counts is None:
            return 0
        self.counts.append(count)
        return -count % self.chunk_rows

    def _size(self, index: int, size: tuple) -> None:
        """Make the array at image ``index``'s mask ``size``, or check it is the same."""
        if self.writer is None:
            stores.set_attrs(self.group, mask_height=size[0], mask_width=size[1])
            row_bytes = (size[0] * size[1] + 7) // 8
            flat = stores.FLAT_CHUNK_KEYS if self.counts is not None else None  # per_image
            self.writer = stores.RaggedWriter(
                self.group,
                "masks",
                (row_bytes,),
                np.uint8,
                self.chunk_rows,
                chunk_key_encoding=flat,
            )
            self.size = tuple(size)
        elif tuple(size) != self.size:
            raise ValueError(
                f"{self.dataset.paths[index]}: masks of size {tuple(size)} differ from the "
                f"first image's {self.size}"
            )

    def _queue(self, rows: int, append, *args) -> None:
        self._wait()  # in order, one call ahead at most
        self._pending = self._packing.submit(append, *args)
        self.rows += rows

    def _wait(self) -> None:
        """Wait for the last append; re-raise its error."""
        if self._pending is not None:
            pending, self._pending = self._pending, None
            pending.result()


def _mask_size(group: stores.CheckedGroup) -> tuple[int, int]:
    return int(group.attrs["mask_height"]), int(group.attrs["mask_width"])


def _append_packed(writer: stores.RaggedWriter, masks: np.ndarray, padding: int) -> None:
    writer.append(_padded(stores.pack_masks(masks), padding))


def _padded(rows: np.ndarray, padding: int) -> np.ndarray:
    """Packed mask ``rows`` followed by ``padding`` empty ones (per_image)."""
    if not padding:
        return rows
    return np.concatenate([rows, np.zeros((padding, rows.shape[1]), np.uint8)])


def _append_images(writer: stores.RaggedWriter, pieces: list, lengths: np.ndarray) -> None:
    reuse.append_rows(writer, pieces)
    writer.add_images(lengths)


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
