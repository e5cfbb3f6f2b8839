"""Image segmenters producing (possibly overlapping) boolean masks.

A segmenter maps an image ``[H, W, 3]`` (float32 in ``[0, 1]``) to masks
``[S, H, W]``. The scikit-image segmenters (``slic``, ``felzenszwalb``) partition the
image; Segment Anything (``sam``, ``sam_hq``, ``sam2``: ``vprflow.models.sam.generator`` over
``vprflow.models.sam.adapters``) returns overlapping masks.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from vprflow.models.kinds import SEGMENTERS, with_defaults

_SLIC = SEGMENTERS["slic"].defaults
_FELZENSZWALB = SEGMENTERS["felzenszwalb"].defaults


class Segmenter(Protocol):
    def masks(self, image: np.ndarray) -> np.ndarray: ...


def labels_to_masks(labels: np.ndarray) -> np.ndarray:
    """Label image ``[H, W]`` -> one boolean mask per distinct label ``[S, H, W]``."""
    values = np.unique(labels)
    return labels[None, :, :] == values[:, None, None]


class SlicSegmenter:
    def __init__(
        self,
        n_segments: int = _SLIC["n_segments"],
        compactness: float = _SLIC["compactness"],
        sigma: float = _SLIC["sigma"],
    ):
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
    def __init__(
        self,
        scale: float = _FELZENSZWALB["scale"],
        sigma: float = _FELZENSZWALB["sigma"],
        min_size: int = _FELZENSZWALB["min_size"],
    ):
        self.scale, self.sigma, self.min_size = scale, sigma, min_size

    def masks(self, image: np.ndarray) -> np.ndarray:
        from skimage.segmentation import felzenszwalb

        labels = felzenszwalb(
            image, scale=self.scale, sigma=self.sigma, min_size=self.min_size, channel_axis=-1
        )
        return labels_to_masks(labels)


def load_slic(params: dict, device: str = "auto") -> SlicSegmenter:
    params = with_defaults("segments", params)
    return SlicSegmenter(**{k: params[k] for k in ("n_segments", "compactness", "sigma")})


def load_felzenszwalb(params: dict, device: str = "auto") -> FelzenszwalbSegmenter:
    params = with_defaults("segments", params)
    return FelzenszwalbSegmenter(**{k: params[k] for k in ("scale", "sigma", "min_size")})
