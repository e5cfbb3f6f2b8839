"""The ``dataset`` rule: image lists, sizes and ground truth of one dataset."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from tqdm import tqdm

from vprflow import datasets, stores
from vprflow.images import read_image
from vprflow.stages.base import shard_range

log = logging.getLogger("vprflow")


def build_dataset(name: str, params: dict, data_root: str, out: str) -> None:
    """List and decode every image once (so a corrupt file fails here, by name) and
    store paths (relative to ``data_root``, so the data folder may move), sizes and
    ground truth. The absolute folder read is logged and kept in the attributes."""
    spec = params["params"]
    files = datasets.list_dataset(data_root, name, spec)
    folder = datasets.dataset_folder(data_root, spec)
    truth = datasets.ground_truth(files, spec["ground_truth"], folder)
    paths = files.reference + files.query
    sizes = np.zeros((len(paths), 2), dtype=np.int64)
    for i, path in enumerate(tqdm(paths, desc=f"checking {name} images")):
        sizes[i] = read_image(path).shape[:2]
    counts = np.array([len(t) for t in truth], dtype=np.int64)
    with stores.atomic_store(out, {"stage": "dataset", "params": params}) as group:
        group.attrs.update(
            name=name,
            data_root_at_build=str(Path(data_root).resolve()),
            n_reference=len(files.reference),
            n_query=len(files.query),
            ground_truth_rule=datasets.ground_truth_rule(spec["ground_truth"]),
            n_queries_with_positives=int((counts > 0).sum()),
        )
        stores.write_array(
            group, "paths", np.array([p.relative_to(data_root).as_posix() for p in paths])
        )
        # Names relative to the dataset folder: "ref/0001.jpg", "query/2024/0001.jpg".
        stores.write_array(
            group, "names", np.array([p.relative_to(folder).as_posix() for p in paths])
        )
        stores.write_array(group, "image_sizes", sizes)
        stores.write_array(
            group, "truth", np.concatenate(truth) if truth else np.zeros(0, np.int64)
        )
        stores.write_array(group, "truth_offsets", np.r_[0, np.cumsum(counts)].astype(np.int64))
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


class Dataset:
    """Read-side view of a dataset store. ``paths`` are the image files under
    ``data_root`` (relative to it when none is given)."""

    def __init__(self, path: str, data_root: str | None = None):
        self.group = stores.open_store(path)
        self.n_reference = int(self.group.attrs["n_reference"])
        self.n_query = int(self.group.attrs["n_query"])
        self.n_images = self.n_reference + self.n_query
        relative = stores.read_strings(self.group, "paths")
        root = Path(data_root) if data_root is not None else None
        self.paths = [str(root / p) if root else p for p in relative]
        self.names = stores.read_strings(self.group, "names")

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
    dataset_path: str, data_root: str, start: int | None, stop: int | None
) -> tuple[Dataset, range]:
    """The dataset (image paths under ``data_root``) and the images ``start..stop`` a
    per-image stage reads; logs the folder it reads from."""
    dataset = Dataset(dataset_path, data_root)
    log.info("reading images under %s", Path(data_root).resolve())
    return dataset, shard_range(dataset.n_images, start, stop)
