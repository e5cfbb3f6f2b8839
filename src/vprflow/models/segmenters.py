"""Image segmenters producing (possibly overlapping) boolean masks.

A segmenter maps an image ``[H, W, 3]`` (float32 in ``[0, 1]``) to masks
``[S, H, W]``. The scikit-image segmenters (``slic``, ``felzenszwalb``) partition the
image; Segment Anything (``sam``, ``sam_hq``, ``sam2``: ``vprflow.models.sam.generator`` over
``vprflow.models.sam.adapters``) returns overlapping masks.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from vprflow.core.lazy import lazy_import
from vprflow.models.kinds import SEGMENTERS, with_defaults

color = lazy_import("skimage.color")
colorconv = lazy_import("skimage.color.colorconv")
segmentation = lazy_import("skimage.segmentation")

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
        # The module itself, not a lazy_import stand-in: its rgb2lab is replaced below,
        # and a name set on a stand-in stays there (slic would not see it).
        from skimage.segmentation import slic_superpixels

        # slic converts to Lab inside, after rescaling the image: its conversion is
        # replaced for the call, there being no argument for it.
        published = slic_superpixels.rgb2lab
        slic_superpixels.rgb2lab = rgb_to_lab
        try:
            labels = segmentation.slic(
                image,
                n_segments=self.n_segments,
                compactness=self.compactness,
                sigma=self.sigma,
                start_label=0,
                channel_axis=-1,
            )
        finally:
            slic_superpixels.rgb2lab = published
        return labels_to_masks(labels)


def rgb_to_lab(rgb: np.ndarray) -> np.ndarray:
    """scikit-image's ``rgb2lab`` (D65, 2 degrees) of ``rgb`` ``[..., 3]`` in its dtype,
    but the RGB -> XYZ product taken elementwise in float64 and rounded once: rgb2lab
    takes it as a matrix product in the image's dtype through BLAS, whose rounding moves
    with the kernel (SLIC's segments of roadscene's thermal queries moved with it)."""
    arr = np.array(rgb, dtype=np.result_type(rgb, np.float32))
    # rgb2xyz's sRGB linearisation, in the image's dtype as there.
    bright = arr > 0.04045
    arr[bright] = np.power((arr[bright] + 0.055) / 1.055, 2.4)
    arr[~bright] /= 12.92
    linear = arr.astype(np.float64)
    r, g, b = linear[..., 0], linear[..., 1], linear[..., 2]
    xyz = np.stack([m[0] * r + m[1] * g + m[2] * b for m in colorconv.xyz_from_rgb], axis=-1)
    return color.xyz2lab(xyz.astype(arr.dtype))


class FelzenszwalbSegmenter:
    def __init__(
        self,
        scale: float = _FELZENSZWALB["scale"],
        sigma: float = _FELZENSZWALB["sigma"],
        min_size: int = _FELZENSZWALB["min_size"],
    ):
        self.scale, self.sigma, self.min_size = scale, sigma, min_size

    def masks(self, image: np.ndarray) -> np.ndarray:
        labels = segmentation.felzenszwalb(
            image, scale=self.scale, sigma=self.sigma, min_size=self.min_size, channel_axis=-1
        )
        return labels_to_masks(labels)


def load_slic(params: dict, device: str = "auto") -> SlicSegmenter:
    params = with_defaults("segments", params)
    return SlicSegmenter(**{k: params[k] for k in ("n_segments", "compactness", "sigma")})


def load_felzenszwalb(params: dict, device: str = "auto") -> FelzenszwalbSegmenter:
    params = with_defaults("segments", params)
    return FelzenszwalbSegmenter(**{k: params[k] for k in ("scale", "sigma", "min_size")})
