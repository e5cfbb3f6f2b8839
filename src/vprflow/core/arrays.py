"""Small array helpers that several modules share. A leaf: imports nothing from vprflow."""

from __future__ import annotations

import numpy as np


def l2_normalize(x: np.ndarray, axis: int = -1, eps: float = 1e-12) -> np.ndarray:
    """``x`` divided by its L2 norm along ``axis`` (norms below ``eps`` count as ``eps``)."""
    return x / np.maximum(np.linalg.norm(x, axis=axis, keepdims=True), eps)


def center_offset(size: int, kept: int) -> int:
    """Where a centred window of ``kept`` pixels starts in ``size``: rounded like
    torchvision's ``CenterCrop`` (Python ``round``, half to even), as published."""
    return int(round((size - kept) / 2.0))


def center_crop_box(height: int, width: int, patch: int) -> tuple[int, int, int, int]:
    """``(top, left, crop_height, crop_width)`` of the patch-multiple centre crop.

    Offsets round as :func:`center_offset`. Every backbone crops with this, and SegVLAD's
    ``crop_aligned`` mask mapping shifts by the same offsets (docs/methods.md §1).
    Raises ``ValueError`` when the image is smaller than one patch.
    """
    crop_h, crop_w = (height // patch) * patch, (width // patch) * patch
    if crop_h == 0 or crop_w == 0:
        raise ValueError(
            f"input size {width}x{height} (width x height) is smaller than one {patch}x{patch} "
            "patch: raise the dataset's `resolution` (or the backbone entry's)"
        )
    return center_offset(height, crop_h), center_offset(width, crop_w), crop_h, crop_w
