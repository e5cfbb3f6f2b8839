"""Every store's read side, in one place: what the stages after a store read of it, and
the array names and formats its writer and its readers share. A stage's runner imports
these readers, never another runner."""

from __future__ import annotations

import hashlib
import logging
import os
from pathlib import Path

import numpy as np

from vprflow.aggregation.pca import Pca
from vprflow.core import reuse, stores
from vprflow.core.errors import DatasetError
from vprflow.data.images import ImageReadError, decode_image
from vprflow.models.kinds import model_kind
from vprflow.stages.base import Job, shard_range

log = logging.getLogger("vprflow")


# What the truth store copies of the images store, so its readers read one store.
IMAGE_ARRAYS = ("paths", "names", "sha256", "image_sizes")


def read_image_bytes(path: Path) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError as error:
        raise ImageReadError(f"cannot read image {path}: {error}") from error


class Dataset:
    """Read-side view of an images or dataset store (the ground truth: only the
    latter). ``paths`` are the image files under ``data_root`` (relative to it when none
    is given)."""

    def __init__(self, path: str, data_root: str | None = None):
        self.group = stores.open_store(path)
        self._sha256: list[str] | None = None
        self.n_reference = int(self.group.attrs["n_reference"])
        self.n_query = int(self.group.attrs["n_query"])
        self.n_images = self.n_reference + self.n_query
        relative = stores.read_strings(self.group, "paths")
        # str(Path(root) / path) for each, a tenth of its time on 2,000 images.
        root = os.path.join(str(Path(data_root)), "") if data_root is not None else ""
        self.paths = [root + path for path in relative] if root != "./" else relative
        self.names = stores.read_strings(self.group, "names")
        self.exif_orientation = self.group.attrs["exif_orientation"]

    def read_image(self, index: int, exif_orientation: str | None = None) -> np.ndarray:
        """Image ``index`` as :func:`vprflow.data.images.read_image` decodes it, with
        ``exif_orientation`` (a method's stage passes its own) or the dataset's, after
        checking that the file still holds what the images stage hashed: an image
        changed during a run must fail, naming it, not be computed under the key of its
        old content."""
        path = self.paths[index]
        data = read_image_bytes(Path(path))
        if self._sha256 is None:
            self._sha256 = stores.read_strings(self.group, "sha256")
        if hashlib.sha256(data).hexdigest() != self._sha256[index]:
            raise DatasetError(
                f"{path} changed after the images stage read it (its SHA-256 differs), so "
                "results computed now would be stored under its old content's key. Run "
                "snakemake again: it re-plans and rebuilds what depends on the image"
            )
        return decode_image(data, path, exif_orientation or self.exif_orientation)

    @property
    def has_ground_truth(self) -> bool:
        """False for ``ground_truth: {kind: none}``: rankings, but nothing to judge them by."""
        return self.group.attrs["ground_truth_rule"] != "none"

    def truth(self) -> list[np.ndarray]:
        refs = np.asarray(self.group["truth"][...])
        offsets = np.asarray(self.group["truth_offsets"][...])
        return [refs[offsets[q] : offsets[q + 1]] for q in range(self.n_query)]

    def indices(self, which: str) -> np.ndarray:
        return {
            "reference": np.arange(self.n_reference),
            "query": np.arange(self.n_reference, self.n_images),
            "both": np.arange(self.n_images),
        }[which]


def open_shard(
    images_path: str, data_root: str, start: int | None, stop: int | None
) -> tuple[Dataset, range]:
    """The images store (image paths under ``data_root``) and the images ``start..stop``
    a per-image stage reads; logs the folder it reads from."""
    dataset = Dataset(images_path, data_root)
    log.info("reading images under %s", Path(data_root).resolve())
    return dataset, shard_range(dataset.n_images, start, stop)


def read_features(group, index: int) -> np.ndarray:
    """float32 ``[h, w, D]`` of one image of a features store."""
    return np.asarray(group["features"][index], dtype=np.float32)


class FeatureReader:
    """``reader(index) -> float32 [h, w, D]``, read-only, reading about ``block_bytes``
    of images per store access: a per-image stage walks the images in order, and one
    store read per image costs more than the arithmetic on it for small grids.

    An image is a read-only view of its block, not a copy, and blocks stay small enough
    for the allocator to reuse the last one's memory (glibc maps anything above 32 MiB
    afresh, and touching new pages costs more than a copy). Reading 2,048 DAISY images
    of 125 KB (with the row reader's direct reads), ms an image: copies from 64 MiB
    blocks 0.064, views 0.056; views from 8 MiB blocks 0.047, from 2 MiB 0.044."""

    def __init__(self, group, block_bytes: int = 4 << 20):
        self.array = group["features"]
        per_image = 4 * int(np.prod(self.array.shape[1:]))
        self.block = max(1, block_bytes // max(per_image, 1))
        self.start, self.cached = 0, np.zeros((0,), np.float32)

    def __call__(self, index: int) -> np.ndarray:
        if not self.start <= index < self.start + len(self.cached):
            self.start = index
            stop = min(index + self.block, self.array.shape[0])
            self.cached = np.asarray(self.array[index:stop], dtype=np.float32)
            self.cached.flags.writeable = False
        return self.cached[index - self.start]


def read_masks(group, index: int) -> np.ndarray:
    """bool ``[S, Hm, Wm]`` of one image of a segments store."""
    return MaskReader(group)(index)


class MaskReader:
    """``reader(index) -> bool [S, Hm, Wm]``, reading the packed masks of many images
    per store access (see :class:`vprflow.core.stores.RaggedReader`), in either layout
    (:mod:`vprflow.core.masks`)."""

    def __init__(self, group):
        self.packed = stores.RaggedReader(group, "masks")
        self.counts = mask_rows(group)[1]
        self.height, self.width = int(group.attrs["mask_height"]), int(group.attrs["mask_width"])

    def __call__(self, index: int) -> np.ndarray:
        rows = self.packed(index)[: self.counts[index]]  # per_image: less the padding
        return stores.unpack_masks(rows, self.height, self.width)


def mask_rows(group) -> tuple[np.ndarray, np.ndarray]:
    """``(offsets [n + 1], counts [n])`` of a segments store's masks: image ``i``'s are
    rows ``offsets[i]:offsets[i] + counts[i]`` of ``masks``. Packed, its rows are its
    masks (``counts`` the offsets' steps); per_image (:mod:`vprflow.core.masks`),
    ``masks_counts`` says how many of its rows are masks, the rest padding."""
    offsets = np.asarray(group["masks_offsets"][...])
    if "masks_counts" in group:
        return offsets, np.asarray(group["masks_counts"][...])
    return offsets, np.diff(offsets)


def segment_offsets(group) -> np.ndarray:
    """``[n + 1]``: image ``i``'s segments are ``offsets[i]:offsets[i + 1]`` of all the
    store's segments counted in image order, in either layout."""
    return np.concatenate([[0], np.cumsum(mask_rows(group)[1])]).astype(np.int64)


def read_centres(path: str) -> np.ndarray:
    return np.asarray(stores.open_store(path)["centres"][...], dtype=np.float32)


def read_pca(path: str):

    group = stores.open_store(path)
    return Pca(
        mean=np.asarray(group["mean"][...]),
        components=np.asarray(group["components"][...]),
        explained_variance=np.asarray(group["explained_variance"][...]),
        whiten=bool(group.attrs["whiten"]),
    )


def read_search(path: str) -> tuple[np.ndarray, np.ndarray]:
    """``(distances [Sq, k], indices [Sq, k])`` of a merged search store."""
    group = stores.open_store(path)
    return np.asarray(group["distances"][...]), np.asarray(group["indices"][...])


# The pairs' arrays, one row a pair, in (query, candidate, increasing query patch) order.
PAIR_ARRAYS = {"query_patch": np.int32, "candidate_patch": np.int32, "similarity": np.float32}


class Matches:
    """A ``matches`` store read query by query: :meth:`pairs` gives one query's
    candidates' pairs as :func:`vprflow.evaluation.rerank.candidate_pairs` does, reading
    the pairs about 64 MiB at a time (queries are read in order)."""

    def __init__(self, path: str):
        self.group = stores.open_store(path)
        attrs = self.group.attrs
        self.grid = tuple(int(v) for v in attrs["grid"])
        self.patch = int(attrs["patch_size"])
        self.top_k = int(attrs["top_k"])
        self.retrieval_ranking = np.asarray(self.group["retrieval_ranking"][...])
        self.offsets = np.asarray(self.group["offsets"][...])
        n_query = len(self.retrieval_ranking)
        if len(self.offsets) != n_query * self.top_k + 1:
            raise stores.StoreCorruptError(
                path,
                f"offsets has {len(self.offsets)} entries, not {n_query} queries x "
                f"{self.top_k} candidates + 1",
            )
        self._arrays = {name: self.group[name] for name in PAIR_ARRAYS}
        self._block = (64 << 20) // sum(np.dtype(d).itemsize for d in PAIR_ARRAYS.values())
        self._start, self._rows = 0, {name: np.zeros(0, d) for name, d in PAIR_ARRAYS.items()}

    def candidates(self, q: int) -> np.ndarray:
        """Query ``q``'s candidates ``[k]`` (reference indices; the top ``top_k`` present)."""
        head = self.retrieval_ranking[q, : self.top_k]
        return head[head >= 0]

    def pairs(self, q: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """``[(query_patch [M] int32, candidate_patch [M] int32, similarity [M] float32)]``,
        one per candidate of :meth:`candidates`."""
        first = q * self.top_k
        low, high = int(self.offsets[first]), int(self.offsets[first + self.top_k])
        stop = self._start + len(self._rows["similarity"])
        if not (self._start <= low and high <= stop):
            # This query's pairs and those after it, about 64 MiB.
            stop = max(high, min(low + self._block, int(self.offsets[-1])))
            self._start = low
            self._rows = {n: np.asarray(a[low:stop]) for n, a in self._arrays.items()}
        rows = [self._rows[name] for name in PAIR_ARRAYS]
        slots = first + np.flatnonzero(self.retrieval_ranking[q, : self.top_k] >= 0)
        return [
            tuple(
                r[int(self.offsets[c]) - self._start : int(self.offsets[c + 1]) - self._start]
                for r in rows
            )
            for c in slots
        ]


def reusable_results(job: Job, dataset, images: range) -> dict[int, reuse.Source]:
    """Where finished stores of a per-image stage (features, segments) hold the results
    of the job's ``images`` (indices into ``dataset``, its images store open), by image
    (:func:`vprflow.core.reuse.find_sources`); none for a published file's, read by
    image name: they depend on more than the image."""
    if model_kind(job.record["stage"], job.params).reads_file:
        return {}
    digests = stores.read_strings(dataset.group, "sha256")
    return reuse.find_sources(job.inputs["images"], job.record, digests, images)
