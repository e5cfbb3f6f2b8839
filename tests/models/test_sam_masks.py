"""The tensor operations on masks of automatic mask generation (``vprflow.models.sam.masks``)
against direct formulas: ``F.interpolate`` in float64 for the logit upscaling, per-pixel
counts for stability scores and boxes, a pure-Python float64 NMS (:func:`reference_nms`,
also the NMS of ``test_sam_generator``'s reference pipeline).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from vprflow.models.sam.adapters import preprocess_shape
from vprflow.models.sam.masks import (
    LogitUpscaler,
    box_nms,
    masks_to_boxes,
    remove_small_regions,
    stability_score,
)


def reference_nms(boxes: np.ndarray, scores: np.ndarray, threshold: float) -> list[int]:
    """O(n^2) greedy NMS in float64 Python, torchvision semantics (0/0 IoU never suppresses)."""
    order = sorted(range(len(scores)), key=lambda i: (-float(scores[i]), i))
    kept: list[int] = []
    for i in order:
        x0, y0, x1, y1 = (float(v) for v in boxes[i])
        suppressed = False
        for k in kept:
            a0, b0, a1, b1 = (float(v) for v in boxes[k])
            inter = max(0.0, min(x1, a1) - max(x0, a0)) * max(0.0, min(y1, b1) - max(y0, b0))
            union = (x1 - x0) * (y1 - y0) + (a1 - a0) * (b1 - b0) - inter
            if union != 0 and inter / union > threshold:
                suppressed = True
                break
        if not suppressed:
            kept.append(i)
    return kept


# -------------------------------------------------------------------------- upscaling


@pytest.mark.parametrize(
    ("height", "width", "model_size", "low"),
    [(48, 80, 128, 32), (70, 30, 128, 32), (240, 320, 1024, 256), (1100, 700, 1024, 256)],
)
def test_upscaler_equals_interpolate_crop_interpolate(height, width, model_size, low):
    generator = torch.Generator().manual_seed(height)
    logits = torch.randn((5, low, low), generator=generator) * 10
    new_h, new_w = preprocess_shape(height, width, model_size)
    # The reference runs in float64: float32 F.interpolate computes source coordinates in
    # float32 and is itself off by up to 6e-4 at 1024 pixels, a deterministic error that
    # left a float32 comparison only 4x headroom.
    expected = F.interpolate(
        logits.double()[None], (model_size, model_size), mode="bilinear", align_corners=False
    )
    expected = F.interpolate(
        expected[..., :new_h, :new_w], (height, width), mode="bilinear", align_corners=False
    )[0]
    upscale = LogitUpscaler((low, low), model_size, (new_h, new_w), (height, width), "cpu")
    out = upscale(logits)
    assert out.shape == (5, height, width) and out.dtype == torch.float32
    # float32 matrices and matmuls on logits up to ~40 in size: measured within 5e-6 of
    # float64 (about one float32 ulp at 40, 3.8e-6); 1e-4 leaves 20x for other kernels.
    torch.testing.assert_close(out.double(), expected, atol=1e-4, rtol=0)


@pytest.mark.parametrize(("height", "width"), [(48, 80), (240, 320), (1100, 700)])
def test_sam2_upscaler_is_one_bilinear_resize(height, width):
    logits = torch.randn((4, 256, 256), generator=torch.Generator().manual_seed(width)) * 10
    upscale = LogitUpscaler((256, 256), 256, (256, 256), (height, width), "cpu")
    expected = F.interpolate(
        logits.double()[None], (height, width), mode="bilinear", align_corners=False
    )[0]
    torch.testing.assert_close(upscale(logits).double(), expected, atol=1e-4, rtol=0)


# -------------------------------------------------------------------- masks and boxes


def test_stability_score_matches_direct_formula():
    rng = np.random.default_rng(3)
    logits = rng.normal(0, 2, (6, 9, 11)).astype(np.float32)
    logits[5] = -5.0  # nothing above t - offset: 0/0
    for threshold, offset in [(0.0, 1.0), (0.5, 0.25), (-1.0, 2.0)]:
        got = stability_score(torch.from_numpy(logits), threshold, offset).numpy()
        for i, mask in enumerate(logits):
            high = sum(v > threshold + offset for v in mask.ravel())
            low = sum(v > threshold - offset for v in mask.ravel())
            if low == 0:
                assert math.isnan(got[i])
            else:
                assert got[i] == pytest.approx(high / low, rel=1e-6)


def test_masks_to_boxes_inclusive_corners_and_empty():
    masks = torch.zeros((3, 7, 9), dtype=torch.bool)
    masks[0, 2:5, 1:8] = True
    masks[1, 6, 0] = True
    boxes = masks_to_boxes(masks)
    assert boxes.tolist() == [[1, 2, 7, 4], [0, 6, 0, 6], [0, 0, 0, 0]]
    assert boxes.dtype == torch.float32


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("threshold", [0.0, 0.3, 0.5, 0.7, 0.95])
def test_box_nms_matches_python_reference(seed, threshold):
    rng = np.random.default_rng(seed)
    n = 60
    if seed % 2:  # integer boxes as from masks, with repeated scores and degenerate boxes
        corners = rng.integers(0, 30, (n, 2, 2))
        scores = rng.integers(0, 5, n).astype(np.float32)
    else:
        corners = rng.uniform(0, 50, (n, 2, 2))
        scores = rng.uniform(0, 1, n).astype(np.float32)
    boxes = np.concatenate([corners.min(1), corners.max(1)], axis=1)
    boxes = boxes[:, [0, 1, 2, 3]]
    keep = box_nms(torch.from_numpy(boxes).float(), torch.from_numpy(scores), threshold)
    assert keep.dtype == torch.long
    expected = reference_nms(boxes.astype(np.float32).astype(np.float64), scores, threshold)
    assert keep.tolist() == expected
    assert 0 < len(expected) < n or threshold >= 0.95


def test_box_nms_empty_input():
    keep = box_nms(torch.zeros((0, 4)), torch.zeros(0), 0.5)
    assert keep.shape == (0,) and keep.dtype == torch.long


def test_remove_small_regions_holes_and_islands():
    mask = np.zeros((12, 12), dtype=bool)
    mask[1:9, 1:9] = True
    mask[4, 4] = False  # 1-pixel hole
    mask[10, 10] = True  # 1-pixel island
    filled, changed = remove_small_regions(mask, 3, "holes")
    assert changed and filled[4, 4] and filled[10, 10] and filled.sum() == mask.sum() + 1
    cleaned, changed = remove_small_regions(filled, 3, "islands")
    assert changed and not cleaned[10, 10] and cleaned.sum() == 64
    same, changed = remove_small_regions(cleaned, 3, "islands")
    assert not changed and (same == cleaned).all()
    # Every island small: the largest survives.
    dots = np.zeros((8, 8), dtype=bool)
    dots[0, 0] = True
    dots[5:7, 5] = True
    kept, changed = remove_small_regions(dots, 10, "islands")
    assert changed and kept.sum() == 2 and kept[5, 5] and kept[6, 5]
    # 8-connectivity, as OpenCV in the original: a diagonal chain is one region.
    chain = np.zeros((6, 6), dtype=bool)
    chain[[1, 2, 3], [1, 2, 3]] = True
    chain[5, 5] = True
    kept, changed = remove_small_regions(chain, 3, "islands")
    assert changed and kept.sum() == 3 and not kept[5, 5]
