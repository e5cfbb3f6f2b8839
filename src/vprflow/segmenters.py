"""Image segmenters producing (possibly overlapping) boolean masks.

A segmenter maps an image ``[H, W, 3]`` (float32 in ``[0, 1]``) to masks
``[S, H, W]``. The scikit-image segmenters (``slic``, ``felzenszwalb``) partition the
image; Segment Anything (``sam``, in ``vprflow.sam``) returns overlapping masks.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np


class Segmenter(Protocol):
    def masks(self, image: np.ndarray) -> np.ndarray: ...


def labels_to_masks(labels: np.ndarray) -> np.ndarray:
    """Label image ``[H, W]`` -> one boolean mask per distinct label ``[S, H, W]``."""
    values = np.unique(labels)
    return labels[None, :, :] == values[:, None, None]


class SlicSegmenter:
    def __init__(self, n_segments: int = 50, compactness: float = 10.0, sigma: float = 1.0):
        self.n_segments, self.compactness, self.sigma = n_segments, compactness, sigma

    def masks(self, image: np.ndarray) -> np.ndarray:
        from skimage.segmentation import slic

        labels = slic(
            image,
            n_segments=self.n_segments,
            compactness=self.compactness,
            sigma=self.sigma,
            start_label=0,
            channel_axis=-1,
        )
        return labels_to_masks(labels)


class FelzenszwalbSegmenter:
    def __init__(self, scale: float = 100.0, sigma: float = 0.8, min_size: int = 50):
        self.scale, self.sigma, self.min_size = scale, sigma, min_size

    def masks(self, image: np.ndarray) -> np.ndarray:
        from skimage.segmentation import felzenszwalb

        labels = felzenszwalb(
            image, scale=self.scale, sigma=self.sigma, min_size=self.min_size, channel_axis=-1
        )
        return labels_to_masks(labels)


def load_segmenter(params: dict, device: str = "auto") -> Segmenter:
    """Build the segmenter named by ``params['segmenter']``."""
    name = params["segmenter"]
    if name == "slic":
        return SlicSegmenter(
            **{k: params[k] for k in ("n_segments", "compactness", "sigma") if k in params}
        )
    if name == "felzenszwalb":
        return FelzenszwalbSegmenter(
            **{k: params[k] for k in ("scale", "sigma", "min_size") if k in params}
        )
    if name == "sam":
        from vprflow.sam import load_sam

        return load_sam(params, device)
    raise ValueError(f"unknown segmenter {name!r} (expected slic, felzenszwalb or sam)")
