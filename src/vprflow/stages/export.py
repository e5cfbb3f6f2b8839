"""The ``export`` rule: one method's descriptors of a dataset in a single ``.npz`` file.

The file holds plain arrays (read with ``np.load(path)``, no pickle):

- ``names [n]`` image paths relative to the dataset folder, references first;
- ``is_query [n]`` bool;
- ``descriptors``: ``[n, dim]`` for global methods, or ``[S, dim]`` for per-segment
  ones (SegVLAD), whose segments of image ``i`` are rows
  ``offsets[i]:offsets[i + 1]`` (``offsets [n + 1]``);
- ``kind``: ``"global"`` or ``"segments"``; ``method``, ``dataset``.

For data too large for one file, read the Zarr store itself (README: "Reading the
stores").
"""

from __future__ import annotations

import numpy as np

from vprflow import stores
from vprflow.files import atomic_path
from vprflow.stages.dataset import Dataset


def export_descriptors(
    dataset_name: str, method: str, dataset_path: str, descriptors_path: str, out: str
) -> None:
    """Write ``out`` (an ``.npz``) from the dataset and descriptors stores."""
    dataset = Dataset(dataset_path)
    group = stores.open_store(descriptors_path)
    arrays = {
        "names": np.array(dataset.names),
        "is_query": np.arange(dataset.n_images) >= dataset.n_reference,
        "descriptors": np.asarray(group["descriptors"][...]),
        "kind": np.array(group.attrs["kind"]),
        "method": np.array(method),
        "dataset": np.array(dataset_name),
    }
    if group.attrs["kind"] == "segments":
        arrays["offsets"] = np.asarray(group["descriptors_offsets"][...])
    with atomic_path(out, suffix=".npz") as tmp:  # np.savez appends .npz otherwise
        np.savez(tmp, **arrays)
