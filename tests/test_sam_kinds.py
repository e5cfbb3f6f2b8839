"""SAM, SAM-HQ and SAM 2 automatic masks: the per-model adapters and the shared generator.

Tiny random ``SamModel`` / ``SamHQModel`` / ``Sam2Model`` checkpoints are saved and loaded
through the real loader. Three kinds of check:

- end to end: every kind returns boolean masks of the image's size;
- adapters: the low-res logits and IoUs the generator decodes from (embedding computed
  once, prompts in batches through ``vprflow.sam_decoder``) equal one direct call of the
  transformers model on the same pixels and prompts (SAM-HQ: of the original decoder,
  written with the model's modules; see ``test_sam_decoder``);
- shared post-processing: with the adapter's decoder replaced by synthetic low-res
  logits, the generator's output equals a float64 reference that follows each original
  library (SAM / SAM-HQ: upscale to the padded input, crop, resize; SAM 2: one resize;
  SAM-HQ: one candidate per point). ``tests/test_sam.py`` checks SAM itself against a
  float64 reference of the whole pipeline.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from test_sam import mask_box, reference_generate, sample_image
from test_sam_decoder import hq_original
from tiny_models import tiny_sam, tiny_sam2, tiny_sam_hq

from vprflow.registry import SEGMENTERS
from vprflow.sam_adapters import (
    SAM_KINDS,
    load_segmenter,
    preprocess_image_sam2,
    preprocess_shape,
)
from vprflow.sam_masks import LogitUpscaler

KINDS = ("sam", "sam_hq", "sam2")
MODEL_SIZE = 128
SIDE = 8  # points per side: 64 points
BUILD = {"sam": tiny_sam, "sam_hq": tiny_sam_hq, "sam2": tiny_sam2}
# Well-conditioned weights (as test_sam's reference model): float32 logits of separately
# batched calls agree to ~1e-5.
SCALE = 0.3
# Low-res logits of the synthetic decoder: +INSIDE inside a disc, -OUTSIDE elsewhere.
# Bilinear weights here are dyadic / small-denominator rationals, never 5/13, 4/13 or
# 6/13, so no upscaled logit lands on 0 or +-1 (checked in the test).
INSIDE, OUTSIDE = 8.0, 5.0


@pytest.fixture(scope="module", params=KINDS)
def saved(request, tmp_path_factory):
    kind = request.param
    model = BUILD[kind](model_size=MODEL_SIZE, seed=3, scale=SCALE)
    path = tmp_path_factory.mktemp(kind)
    model.save_pretrained(path)
    return kind, path, model


def _load(kind, path, **params):
    return load_segmenter(kind, {"model": str(path), "points_per_side": SIDE, **params}, "cpu")


def test_registry_defaults_are_each_generators_defaults():
    common = {
        "points_per_side": 32,
        "points_per_batch": 64,
        "stability_score_thresh": 0.95,
        "stability_score_offset": 1.0,
        "box_nms_thresh": 0.7,
        "min_mask_region_area": 0,
        "mask_threshold": 0.0,
    }
    for kind in KINDS:
        defaults = SEGMENTERS[kind].defaults
        assert {k: defaults[k] for k in common} == common, kind
        assert SEGMENTERS[kind].loader == f"vprflow.sam_adapters:load_{kind}"
    assert SEGMENTERS["sam"].defaults["pred_iou_thresh"] == 0.88
    assert SEGMENTERS["sam_hq"].defaults["pred_iou_thresh"] == 0.88  # SAM's generator
    assert SEGMENTERS["sam_hq"].defaults["hq_token_only"] is False
    assert SEGMENTERS["sam2"].defaults["pred_iou_thresh"] == 0.8  # SAM 2's own
    assert SEGMENTERS["sam_hq"].defaults["model"] == "syscv-community/sam-hq-vit-huge"
    assert SEGMENTERS["sam2"].defaults["model"] == "facebook/sam2.1-hiera-large"
    assert set(SAM_KINDS) == set(KINDS)


def test_masks_end_to_end(saved):
    kind, path, _ = saved
    segmenter = _load(kind, path, pred_iou_thresh=0.0, stability_score_thresh=0.0)
    assert segmenter.adapter.masks_per_point == (1 if kind == "sam_hq" else 3)
    for height, width in [(48, 80), (70, 30)]:
        result = segmenter.generate(sample_image(height, width))
        masks = result.masks
        assert masks.dtype == bool and masks.shape[1:] == (height, width)
        assert len(masks) > 0 and masks.reshape(len(masks), -1).any(1).all()
        assert (result.candidate < SIDE * SIDE * segmenter.adapter.masks_per_point).all()
    # The library thresholds run too (with random weights few or no masks survive).
    default = _load(kind, path).masks(sample_image())
    assert default.dtype == bool and default.shape[1:] == (48, 80)


def test_bfloat16_runs(saved):
    kind, path, _ = saved
    segmenter = _load(kind, path, pred_iou_thresh=0.0, stability_score_thresh=0.0, dtype="bfloat16")
    masks = segmenter.masks(sample_image())
    assert masks.dtype == bool and masks.shape[1:] == (48, 80)


def test_loaded_with_sdpa_attention(saved):
    kind, path, _ = saved
    assert _load(kind, path).adapter.model.config._attn_implementation == "sdpa"


def _direct(kind, model, pixels, points):
    """One call on pixels and all points -> (logits [P, M, h, w], iou [P, M]): the
    transformers model for SAM and SAM 2; for SAM-HQ the original library's decoder
    written with the model's modules (transformers' differs: see test_sam_decoder)."""
    count = points.shape[0]
    prompts = {
        "input_points": points.float().reshape(1, count, 1, 2),
        "input_labels": torch.ones((1, count, 1), dtype=torch.int64),
    }
    with torch.no_grad():
        if kind == "sam_hq":
            embedding, intermediate = model.get_image_embeddings(pixels)
            sparse, dense = model.prompt_encoder(**prompts, input_boxes=None, input_masks=None)
            inputs = {
                "embedding": embedding,
                "intermediate": intermediate,
                "image_pe": model.get_image_wide_positional_embeddings(),
                "sparse": sparse,
                "dense": dense,
            }
            return hq_original(model.mask_decoder, inputs, hq_token_only=False)
        out = model(pixel_values=pixels, **prompts, multimask_output=True)
    return out.pred_masks[0], out.iou_scores[0]


def test_adapter_decode_equals_a_direct_model_call(saved):
    kind, path, model = saved
    segmenter = _load(kind, path, points_per_batch=7)
    image = sample_image()
    embedding, input_size = segmenter.image_embedding(image)
    _, model_points = segmenter.prompt_points(48, 80, input_size)
    points = torch.from_numpy(model_points)
    got_logits, got_iou = zip(
        *(segmenter.decode(embedding, points[s : s + 7]) for s in range(0, len(points), 7)),
        strict=True,
    )
    pixels, _ = segmenter.adapter.preprocess(image)
    logits, iou = _direct(kind, model, pixels, points)
    per_point = segmenter.adapter.masks_per_point
    assert logits.shape[:2] == (SIDE * SIDE, per_point)
    # float32 on both sides, different batching and attention kernels (sdpa vs the
    # model's default): measured within ~1e-5 with these weights.
    torch.testing.assert_close(torch.cat(got_logits), logits, atol=1e-3, rtol=1e-3)
    torch.testing.assert_close(torch.cat(got_iou), iou, atol=1e-3, rtol=1e-3)
    assert logits.abs().max() > 0.05, "logits degenerate"


def test_sam2_preprocessing_stretches_and_normalises():
    image = sample_image(30, 50)
    pixels, size = preprocess_image_sam2(image, 64)
    assert pixels.shape == (1, 3, 64, 64) and size == (64, 64)
    flat = np.full((20, 10, 3), 0.5, dtype=np.float32)
    pixels, _ = preprocess_image_sam2(flat, 32)
    expected = (np.rint(0.5 * 255) / 255 - np.array([0.485, 0.456, 0.406])) / np.array(
        [0.229, 0.224, 0.225]
    )
    np.testing.assert_allclose(pixels[0, :, 5, 7].numpy(), expected, atol=1e-6)
    # Upsampling: antialiasing is inactive, so this is plain bilinear on the 8-bit image.
    quantised = torch.from_numpy(np.rint(image * 255) / 255).float().permute(2, 0, 1)[None]
    plain = F.interpolate(quantised, (64, 64), mode="bilinear", align_corners=False)
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    got, _ = preprocess_image_sam2(image, 64)
    torch.testing.assert_close(got, (plain - mean) / std, atol=1e-5, rtol=0)


@pytest.mark.parametrize(("height", "width"), [(48, 80), (240, 320), (1100, 700)])
def test_sam2_upscaler_is_one_bilinear_resize(height, width):
    logits = torch.randn((4, 256, 256), generator=torch.Generator().manual_seed(width)) * 10
    upscale = LogitUpscaler((256, 256), 256, (256, 256), (height, width), "cpu")
    expected = F.interpolate(
        logits.double()[None], (height, width), mode="bilinear", align_corners=False
    )[0]
    torch.testing.assert_close(upscale(logits).double(), expected, atol=1e-4, rtol=0)


# ------------------------------------------------- shared post-processing, synthetic logits

LOW = 32  # synthetic low-res logit side


def _synthetic(points: torch.Tensor, per_point: int, model_size: int):
    """Discs around each point (model-input pixels), radius growing with the output index
    -> low-res logits ``[P, M, LOW, LOW]`` float32 and IoUs ``[P, M]`` on a 1/64 grid
    (ties included: they keep candidate order)."""
    ys, xs = torch.meshgrid(torch.arange(LOW), torch.arange(LOW), indexing="ij")
    logits, ious = [], []
    for x, y in points.double().tolist():
        index = int(x * 7 + y * 13)  # from the point, not its place in the batch
        cx, cy = x / model_size * LOW - 0.5, y / model_size * LOW - 0.5
        row, row_iou = [], []
        for m in range(per_point):
            radius = 2 + 3 * m + (index % 3)
            inside = (xs - cx) ** 2 + (ys - cy) ** 2 <= radius**2
            row.append(torch.where(inside, INSIDE, -OUTSIDE))
            row_iou.append(((index * 37 + m * 11) % 64) / 64)
        logits.append(torch.stack(row))
        ious.append(row_iou)
    return torch.stack(logits).float(), torch.tensor(ious, dtype=torch.float32)


def _reference_upscale(kind, low, model_size, input_size, size):
    low = low.double()[None]
    if kind == "sam2":
        return F.interpolate(low, size, mode="bilinear", align_corners=False)[0]
    up = F.interpolate(low, (model_size, model_size), mode="bilinear", align_corners=False)
    up = up[..., : input_size[0], : input_size[1]]
    return F.interpolate(up, size, mode="bilinear", align_corners=False)[0]


@pytest.mark.parametrize(
    ("iou_thresh", "stab_thresh", "nms_thresh"),
    [(0.0, 0.0, 1.0), (0.7, 0.0, 0.7), (0.0, 0.9, 0.5), (0.3, 0.85, 0.3)],
)
def test_shared_post_processing_on_synthetic_logits(saved, iou_thresh, stab_thresh, nms_thresh):
    kind, path, _ = saved
    height, width = 48, 80
    segmenter = _load(
        kind,
        path,
        pred_iou_thresh=iou_thresh,
        stability_score_thresh=stab_thresh,
        box_nms_thresh=nms_thresh,
        points_per_batch=10,  # not a divisor of 64: a ragged last batch
    )
    adapter = segmenter.adapter
    per_point, model_size = adapter.masks_per_point, adapter.model_size
    adapter.decode = lambda embedding, points: _synthetic(points, per_point, model_size)
    input_size = (
        (model_size, model_size) if kind == "sam2" else preprocess_shape(height, width, model_size)
    )
    _, model_points = segmenter.prompt_points(height, width, input_size)
    low, iou = _synthetic(torch.from_numpy(model_points), per_point, model_size)
    logits = _reference_upscale(kind, low.flatten(0, 1), model_size, input_size, (height, width))
    distance = torch.stack([(logits - t).abs() for t in (-1.0, 0.0, 1.0)]).min()
    assert distance > 1e-3, "a synthetic logit lies on a threshold: the test is ill-posed"

    expected = reference_generate(
        logits, iou.flatten().double(), iou_thresh, stab_thresh, nms_thresh
    )
    result = segmenter.generate(sample_image(height, width))
    assert result.candidate.tolist() == expected
    assert len(expected) >= 2
    reference_masks = (logits[expected] > 0).numpy()
    assert (result.masks == reference_masks).all()
    assert result.boxes.tolist() == [list(mask_box(m)) for m in reference_masks]
    np.testing.assert_array_equal(result.iou_preds, iou.flatten().numpy()[expected])
    point = result.candidate // per_point
    np.testing.assert_allclose(result.points[:, 0], (point % SIDE + 0.5) / SIDE * width, atol=1e-4)
    np.testing.assert_allclose(
        result.points[:, 1], (point // SIDE + 0.5) / SIDE * height, atol=1e-4
    )


def test_generate_batch_equals_one_image_at_a_time(saved):
    """One encoder pass over images of different sizes gives each image's own masks.

    In float64 (model cast after loading) the batched encoder's rounding differs from
    the single-image one by ~1e-15, far below any decision the generator makes.
    """
    kind, path, _ = saved
    segmenter = _load(kind, path, pred_iou_thresh=0.0, stability_score_thresh=0.0)
    segmenter.adapter.model.double()
    segmenter.adapter.dtype = torch.float64
    images = [
        sample_image(48, 80, seed=1),
        sample_image(70, 30, seed=2),
        sample_image(48, 80, seed=3),
    ]
    batched = segmenter.generate_batch(images)
    assert len(batched) == 3
    for image, result in zip(images, batched, strict=True):
        alone = segmenter.generate(image)
        assert result.masks.shape[1:] == image.shape[:2] and len(result.masks) > 0
        assert result.candidate.tolist() == alone.candidate.tolist()
        np.testing.assert_array_equal(result.masks, alone.masks)
        np.testing.assert_allclose(result.iou_preds, alone.iou_preds, rtol=0, atol=1e-6)
    # masks_batch is the masks of generate_batch.
    for masks, result in zip(segmenter.masks_batch(images[:2]), batched, strict=False):
        np.testing.assert_array_equal(masks, result.masks)
