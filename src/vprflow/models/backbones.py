"""Dense patch-feature backbones.

A backbone turns a batch of images ``[B, H, W, 3]`` (float32 in ``[0, 1]``) into a
grid of patch descriptors ``[B, h, w, D]`` with ``h = H // patch_size`` and
``w = W // patch_size`` (the image is centre-cropped to whole patches).

``daisy`` is weight-free: scikit-image's dense DAISY sampled at the centre of every
patch, a classical dense-VLAD baseline. ``dinov2`` and ``dino`` are the foundation
models of the published pipelines (``vprflow.models.vit``); :mod:`vprflow.models.loaders`
says which loader builds which kind.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from vprflow.core.arrays import center_crop_box, l2_normalize
from vprflow.core.lazy import lazy_import
from vprflow.models.kinds import BACKBONES, with_defaults

feature = lazy_import("skimage.feature")

_DAISY = BACKBONES["daisy"].defaults


class Backbone(Protocol):
    patch_size: int

    def features(self, batch: np.ndarray) -> np.ndarray: ...


# skimage's rgb2gray weights (ITU-R BT.709 luma).
GREY_WEIGHTS = (0.2125, 0.7154, 0.0721)


def grey_image(image: np.ndarray) -> np.ndarray:
    """``image`` ``[H, W, 3]`` -> its grey levels ``[H, W]`` float64, as skimage's
    ``rgb2gray`` weighs the channels but in float64 and elementwise: rgb2gray takes a
    matrix product in the image's dtype through BLAS, whose rounding changes with the
    kernel (float32 images differed by up to 1e-7 between two kernels of one CPU, and
    DAISY and the vocabulary after them)."""
    rgb = np.asarray(image, dtype=np.float64)
    r, g, b = GREY_WEIGHTS
    return r * rgb[..., 0] + g * rgb[..., 1] + b * rgb[..., 2]


class DaisyBackbone:
    """Dense DAISY descriptors, one per ``patch_size`` x ``patch_size`` patch.

    The grey image is reflect-padded so that a descriptor is sampled at the centre of
    every patch of the centre-cropped grid, including the border patches.
    """

    def __init__(
        self,
        patch_size: int = _DAISY["patch_size"],
        radius: int = _DAISY["radius"],
        rings: int = _DAISY["rings"],
        histograms: int = _DAISY["histograms"],
        orientations: int = _DAISY["orientations"],
        normalize: bool = True,
    ):
        if radius < patch_size // 2:
            raise ValueError(f"daisy radius {radius} must be at least half the patch size")
        self.patch_size = patch_size
        self.radius = radius
        self.rings = rings
        self.histograms = histograms
        self.orientations = orientations
        self.normalize = normalize

    @property
    def dim(self) -> int:
        return (self.rings * self.histograms + 1) * self.orientations

    def _one(self, image: np.ndarray) -> np.ndarray:
        p, r = self.patch_size, self.radius
        top, left, crop_h, crop_w = center_crop_box(image.shape[0], image.shape[1], p)
        h, w = crop_h // p, crop_w // p
        grey = grey_image(image[top : top + crop_h, left : left + crop_w])
        # skimage samples at radius + k * step of its input; this padding puts sample
        # (i, j) at the centre of patch (i, j). The extra `p` after keeps the last row.
        before = r - p // 2
        padded = np.pad(grey, ((before, before + p), (before, before + p)), mode="reflect")
        grid = feature.daisy(
            padded,
            step=p,
            radius=r,
            rings=self.rings,
            histograms=self.histograms,
            orientations=self.orientations,
        )[:h, :w]
        # Normalised in float64, then rounded once.
        return (l2_normalize(grid) if self.normalize else grid).astype(np.float32)

    def features(self, batch: np.ndarray) -> np.ndarray:
        return np.stack([self._one(image) for image in batch])


def load_daisy(params: dict, device: str = "auto") -> DaisyBackbone:
    """A :class:`DaisyBackbone` from a ``daisy`` config entry (``device`` is unused)."""
    params = with_defaults("features", params)
    keys = ("patch_size", "radius", "rings", "histograms", "orientations", "normalize")
    return DaisyBackbone(**{k: params[k] for k in keys if k in params})
