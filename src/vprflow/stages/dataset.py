"""A dataset's two stores: ``images`` (what the images are: their list, order, paths,
sizes and SHA-256) and ``dataset`` (what is true about them: the ground truth, with the
images store's arrays copied), and :class:`Dataset`, which reads either."""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path

import numpy as np
from tqdm import tqdm

from vprflow.core import stores
from vprflow.core.errors import DatasetError
from vprflow.core.paths import dataset_folder
from vprflow.data import datasets
from vprflow.data.ground_truth import ground_truth, ground_truth_rule
from vprflow.data.images import dataset_orientation, decode_image
from vprflow.planning.fingerprints import (
    file_digest,
    images_digest,
    load_fingerprints,
    memo_key,
    truth_digest,
)
from vprflow.stages.base import Job
from vprflow.stages.readers import IMAGE_ARRAYS, read_image_bytes

log = logging.getLogger("vprflow")


def build_images(job: Job) -> None:
    """The ``images`` rule: list and decode every image once (so a corrupt file fails
    here, by name) and store paths (relative to ``data_root``, so the data folder may
    move), names, sizes (after the EXIF orientation) and each image's SHA-256. The
    absolute folder read is logged and kept in the attributes.

    What is read must be what the key covers: the images' digest as read here must equal
    the plan's (``record["params"]["contents"]``), else a file changed after planning,
    and it is named (with ``job.fingerprints``, the plan's memo of hashes by file stamp).
    Queries byte-identical to a reference are refused.
    """
    record, data_root, out, params = job.record, job.data_root, job.out, job.params
    name = params["name"]
    files = datasets.list_dataset(data_root, name, params)
    folder = dataset_folder(data_root, params)
    paths = files.reference + files.query
    sizes = np.zeros((len(paths), 2), dtype=np.int64)
    orientation = dataset_orientation(params["exif_orientation"])  # method: upright
    digests = []
    for i, path in enumerate(tqdm(paths, desc=f"checking {name} images")):
        data = read_image_bytes(path)
        digests.append(hashlib.sha256(data).hexdigest())
        sizes[i] = decode_image(data, path, orientation).shape[:2]
    by_path = dict(zip(paths, digests, strict=True))
    contents = images_digest(
        files, data_root, params, lambda p, _: by_path.get(p) or file_digest(p)
    )
    if contents != params["contents"]:
        raise DatasetError(_changed_since_planning(name, paths, by_path, job.fingerprints))
    if "native_size" in params:
        _check_native_size(name, paths, sizes, params["native_size"])
    # A copied folder: the same images under other names.
    datasets.check_disjoint(
        name, files.reference, files.query, by_path.get, "are byte-identical copies of references"
    )
    with stores.atomic_store(out, {"stage": "images", "record": record}) as group:
        stores.set_attrs(
            group,
            name=name,
            data_root_at_build=str(Path(data_root).resolve()),
            n_reference=len(files.reference),
            n_query=len(files.query),
            exif_orientation=orientation,
        )
        stores.write_array(
            group, "paths", np.array([p.relative_to(data_root).as_posix() for p in paths])
        )
        # Names relative to the dataset folder: "ref/0001.jpg", "query/2024/0001.jpg".
        stores.write_array(
            group, "names", np.array([p.relative_to(folder).as_posix() for p in paths])
        )
        stores.write_array(group, "sha256", np.array(digests))
        stores.write_array(group, "image_sizes", sizes)
    for role, (hidden, other) in (files.skipped or {}).items():
        if hidden or other:
            log.warning(
                "dataset %s: %s: skipped %d hidden and %d non-image entries",
                name,
                role,
                hidden,
                other,
            )
    log.info(
        "dataset %s: %d reference, %d query images read from %s",
        name,
        len(files.reference),
        len(files.query),
        folder.resolve(),
    )


def build_dataset(job: Job) -> None:
    """The ``dataset`` rule: the ground truth of the images in the ``images`` input (the
    images store), stored with that store's arrays and counts, so recall, the report and
    the figures read one store. The ground-truth files as read here must hold what the
    key covers (``record["params"]["contents"]``)."""
    record, data_root, out, params = job.record, job.data_root, job.out, job.params
    images = stores.open_store(job.inputs["images"])
    listed = images.attrs["record"]["params"]  # how the images were listed
    name = listed["name"]
    entry = {**listed, "ground_truth": params["ground_truth"]}
    datasets.check_pairing(name, entry)  # pairs match query i with reference i
    if truth_digest(data_root, entry, lambda p, _: file_digest(p)) != params["contents"]:
        raise DatasetError(
            f"dataset '{name}': its ground-truth files changed after this run planned it, so "
            "its key no longer describes them. Run snakemake again: it re-plans, and rebuilds "
            "what depends on the ground truth"
        )
    n_reference = int(images.attrs["n_reference"])
    paths = [Path(data_root) / p for p in stores.read_strings(images, "paths")]
    files = datasets.DatasetFiles(reference=paths[:n_reference], query=paths[n_reference:])
    truth = ground_truth(files, params["ground_truth"], dataset_folder(data_root, entry))
    counts = np.array([len(t) for t in truth], dtype=np.int64)
    with stores.atomic_store(out, {"stage": "dataset", "record": record}) as group:
        stores.set_attrs(
            group,
            name=name,
            data_root_at_build=str(Path(data_root).resolve()),
            n_reference=n_reference,
            n_query=int(images.attrs["n_query"]),
            ground_truth_rule=ground_truth_rule(params["ground_truth"]),
            n_queries_with_positives=int((counts > 0).sum()),
            exif_orientation=images.attrs["exif_orientation"],
        )
        for array in IMAGE_ARRAYS:
            data = np.asarray(images[array][...])
            if data.dtype.kind not in "iuf":  # strings
                data = np.array(stores.read_strings(images, array))
            stores.write_array(group, array, data)
        stores.write_array(
            group, "truth", np.concatenate(truth) if truth else np.zeros(0, np.int64)
        )
        stores.write_array(group, "truth_offsets", np.r_[0, np.cumsum(counts)].astype(np.int64))
    log.info(
        "dataset %s: ground truth %s, %d of %d queries with a positive",
        name,
        ground_truth_rule(params["ground_truth"]),
        int((counts > 0).sum()),
        len(counts),
    )


def _check_native_size(name: str, paths: list[Path], sizes: np.ndarray, size: list[int]) -> None:
    """``resolution: native`` keys later stages by one size (``[width, height]``, the
    first image's at planning time): an image of another size is refused, by name."""
    width, height = size
    wrong = np.flatnonzero((sizes[:, 0] != height) | (sizes[:, 1] != width))
    if len(wrong):
        first = wrong[0]
        raise DatasetError(
            f"dataset {name!r} has resolution: native, planned at {width} x {height} (the size "
            f"of {paths[0]}), but {paths[first]} is {sizes[first, 1]} x {sizes[first, 0]}"
            f"{f' (and {len(wrong) - 1} more images differ)' if len(wrong) > 1 else ''}: "
            "native resolution needs one size for every image; give the dataset a "
            "`resolution: [width, height]` to resize them all"
        )


def _changed_since_planning(
    name: str, paths: list[Path], digests: dict[Path, str], fingerprints: str | None
) -> str:
    """The message for files that differ from what the plan hashed: those whose stamp
    (size, mtime, ctime) or hash is not in the plan's memo."""

    memo = load_fingerprints(fingerprints) if fingerprints else {}
    changed = [p for p in paths if memo.get(memo_key(p)) != digests[p]] if memo else []
    which = f": {', '.join(str(p) for p in changed[:5])}" if changed else ""
    return (
        f"dataset '{name}': files changed after this run planned it, so its key no longer "
        f"describes them{which}. Run snakemake again: it re-plans, and rebuilds what "
        "depends on the changed files"
    )
