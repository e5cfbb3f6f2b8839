"""Dense patch-feature backbones.

A backbone turns a batch of images ``[B, H, W, 3]`` (float32 in ``[0, 1]``) into a
grid of patch descriptors ``[B, h, w, D]`` with ``h = H // patch_size`` and
``w = W // patch_size`` (the image is centre-cropped to whole patches).

``daisy`` is weight-free: scikit-image's dense DAISY sampled at the centre of every
patch, a classical dense-VLAD baseline. ``dinov2`` and ``dino`` are the foundation
models of the published pipelines (``vprflow.vit``).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from vprflow.arrays import center_crop_box, l2_normalize


class Backbone(Protocol):
    patch_size: int

    def features(self, batch: np.ndarray) -> np.ndarray: ...


class DaisyBackbone:
    """Dense DAISY descriptors, one per ``patch_size`` x ``patch_size`` patch.

    The grey image is reflect-padded so that a descriptor is sampled at the centre of
    every patch of the centre-cropped grid, including the border patches.
    """

    def __init__(
        self,
        patch_size: int = 8,
        radius: int = 12,
        rings: int = 2,
        histograms: int = 6,
        orientations: int = 8,
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
        from skimage.color import rgb2gray
        from skimage.feature import daisy

        p, r = self.patch_size, self.radius
        top, left, crop_h, crop_w = center_crop_box(image.shape[0], image.shape[1], p)
        h, w = crop_h // p, crop_w // p
        grey = rgb2gray(image[top : top + crop_h, left : left + crop_w])
        # skimage samples at radius + k * step of its input; this padding puts sample
        # (i, j) at the centre of patch (i, j). The extra `p` after keeps the last row.
        before = r - p // 2
        padded = np.pad(grey, ((before, before + p), (before, before + p)), mode="reflect")
        grid = daisy(
            padded,
            step=p,
            radius=r,
            rings=self.rings,
            histograms=self.histograms,
            orientations=self.orientations,
        )[:h, :w]
        grid = grid.astype(np.float32)
        return l2_normalize(grid) if self.normalize else grid

    def features(self, batch: np.ndarray) -> np.ndarray:
        return np.stack([self._one(image) for image in batch])


def load_backbone(params: dict, device: str = "auto") -> Backbone:
    """Build the backbone named by ``params['backbone']`` (``daisy``, ``dinov2``, ``dino``)."""
    name = params["backbone"]
    if name == "daisy":
        keys = ("patch_size", "radius", "rings", "histograms", "orientations", "normalize")
        return DaisyBackbone(**{k: params[k] for k in keys if k in params})
    if name in ("dinov2", "dino"):
        from vprflow.vit import load_vit

        return load_vit(params, device)
    raise ValueError(f"unknown backbone {name!r} (expected daisy, dinov2 or dino)")
