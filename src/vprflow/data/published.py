"""Reading the Revisit-Anything / AnyLoc authors' preprocessed files.

HDF5 layout (one group per image, named by the image file name):

    <image_name>/ift_dino                      float [1, D, h, w]  dense features
    <image_name>/masks/<j>/segmentation        bool  [H, W]        SAM mask j = 0..S-1

Vocabularies: ``c_centers.pt``, a torch-saved ``[K, D]`` tensor of cluster centres,
or a dict holding exactly one such tensor. Only ``torch.load(..., weights_only=True)``
is used, so a file cannot run code when loaded.

Every error names the file and the missing key.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vprflow.core.lazy import lazy_import

h5py = lazy_import("h5py")
torch = lazy_import("torch")

FEATURES_KEY = "ift_dino"
MASKS_KEY = "masks"
SEGMENTATION_KEY = "segmentation"


class PublishedDataError(LookupError):
    """A published file that lacks an expected entry or has an unexpected shape."""


def _open(h5_path: str | Path):
    path = Path(h5_path)
    if not path.is_file():
        raise FileNotFoundError(f"HDF5 file not found: {path}")
    return h5py.File(path, "r")


def _group(handle, h5_path, image_name: str):
    if image_name not in handle:
        raise PublishedDataError(f"{h5_path}: no group for image {image_name!r}")
    return handle[image_name]


def read_features_h5(h5_path: str | Path, image_name: str) -> np.ndarray:
    """``<image_name>/ift_dino`` ``[1, D, h, w]`` -> float32 ``[h, w, D]``."""
    with _open(h5_path) as handle:
        group = _group(handle, h5_path, image_name)
        if FEATURES_KEY not in group:
            raise PublishedDataError(f"{h5_path}: no dataset {image_name}/{FEATURES_KEY}")
        data = np.asarray(group[FEATURES_KEY][()])
    if data.ndim != 4 or data.shape[0] != 1:
        raise PublishedDataError(
            f"{h5_path}: {image_name}/{FEATURES_KEY} has shape {data.shape}, expected [1, D, h, w]"
        )
    return np.ascontiguousarray(data[0].transpose(1, 2, 0), dtype=np.float32)


def read_masks_h5(h5_path: str | Path, image_name: str) -> np.ndarray:
    """``<image_name>/masks/<j>/segmentation`` for j = 0..S-1 -> bool ``[S, H, W]``.

    Mask keys are decimal strings and are ordered numerically ("10" after "9"). An
    image with a ``masks`` group but no masks gives ``[0, 0, 0]``.
    """
    with _open(h5_path) as handle:
        group = _group(handle, h5_path, image_name)
        if MASKS_KEY not in group:
            raise PublishedDataError(f"{h5_path}: no group {image_name}/{MASKS_KEY}")
        masks_group = group[MASKS_KEY]
        keys = list(masks_group.keys())
        bad = [key for key in keys if not key.isdigit()]
        if bad:
            raise PublishedDataError(
                f"{h5_path}: {image_name}/{MASKS_KEY} has non-numeric keys {bad[:5]}"
            )
        masks = []
        for key in sorted(keys, key=int):
            entry = masks_group[key]
            if SEGMENTATION_KEY not in entry:
                raise PublishedDataError(
                    f"{h5_path}: no dataset {image_name}/{MASKS_KEY}/{key}/{SEGMENTATION_KEY}"
                )
            masks.append(np.asarray(entry[SEGMENTATION_KEY][()]).astype(bool))
    if not masks:
        return np.zeros((0, 0, 0), dtype=bool)
    shapes = {mask.shape for mask in masks}
    if len(shapes) != 1 or masks[0].ndim != 2:
        raise PublishedDataError(
            f"{h5_path}: masks of {image_name!r} are not equal-sized 2-D arrays: {sorted(shapes)}"
        )
    return np.stack(masks)


def load_c_centers(path: str | Path) -> np.ndarray:
    """A torch-saved ``[K, D]`` centre tensor (or a dict holding exactly one) -> float32."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"cluster-centre file not found: {path}")
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # unpickling errors have no common base class
        raise PublishedDataError(
            f"{path}: cannot load with torch.load(weights_only=True): {error}"
        ) from error
    if isinstance(obj, dict):
        tensors = {key: value for key, value in obj.items() if isinstance(value, torch.Tensor)}
        if len(tensors) != 1:
            raise PublishedDataError(
                f"{path}: expected a tensor or a dict with exactly one tensor, found tensor "
                f"keys {sorted(map(str, tensors))}"
            )
        obj = next(iter(tensors.values()))
    if not isinstance(obj, torch.Tensor):
        raise PublishedDataError(f"{path}: expected a tensor, found {type(obj).__name__}")
    if obj.ndim != 2:
        raise PublishedDataError(f"{path}: expected centres [K, D], found shape {tuple(obj.shape)}")
    return obj.detach().to(torch.float32).numpy()
