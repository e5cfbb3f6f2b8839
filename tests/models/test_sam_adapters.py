"""The SAM kinds (``vprflow.models.sam.adapters``): entries (models/kinds.py) and defaults, each
adapter's preprocessing, loading, and prompt decoding.

Tiny random ``SamModel`` / ``SamHQModel`` / ``Sam2Model`` checkpoints (the conftest's
``sam_kind_model``) are saved and loaded through the real loader. The low-res logits and
IoUs the adapters decode (embedding computed once, prompts in batches through
``vprflow.models.sam.decoder``) equal one direct call of the transformers model on the same
pixels and prompts (SAM-HQ: of the original decoder, written with the model's modules;
see ``test_sam_decoder``).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from PIL import Image
from test_sam_decoder import hq_original
from test_sam_generator import sample_image

from vprflow.models.kinds import SEGMENTERS
from vprflow.models.loaders import LOADERS, load_model
from vprflow.models.sam.adapters import (
    PIXEL_MEAN,
    PIXEL_STD,
    SAM_KINDS,
    load_segmenter,
    preprocess_image,
    preprocess_image_sam2,
    preprocess_shape,
)

KINDS = ("sam", "sam_hq", "sam2")
SIDE = 8  # points per side: 64 points


def _load(kind, path, **params):
    return load_segmenter(kind, {"model": str(path), "points_per_side": SIDE, **params}, "cpu")


# --------------------------------------------------------------------------- defaults


def test_defaults_are_the_original_library_defaults():
    defaults = SEGMENTERS["sam"].defaults
    assert defaults["points_per_side"] == 32
    assert defaults["points_per_batch"] == 64
    assert defaults["pred_iou_thresh"] == 0.88
    assert defaults["stability_score_thresh"] == 0.95
    assert defaults["stability_score_offset"] == 1.0
    assert defaults["box_nms_thresh"] == 0.7
    assert defaults["min_mask_region_area"] == 0
    assert defaults["model"] == "facebook/sam-vit-huge"


def test_kind_defaults_are_each_generators_defaults():
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
        assert LOADERS["segments"][kind] is LOADERS["segments"]["sam"]
    assert SEGMENTERS["sam"].defaults["pred_iou_thresh"] == 0.88
    assert SEGMENTERS["sam_hq"].defaults["pred_iou_thresh"] == 0.88  # SAM's generator
    assert SEGMENTERS["sam_hq"].defaults["hq_token_only"] is False
    assert SEGMENTERS["sam2"].defaults["pred_iou_thresh"] == 0.8  # SAM 2's own
    assert SEGMENTERS["sam_hq"].defaults["model"] == "syscv-community/sam-hq-vit-huge"
    assert SEGMENTERS["sam2"].defaults["model"] == "facebook/sam2.1-hiera-large"
    assert set(SAM_KINDS) == set(KINDS)


# ---------------------------------------------------------------------- preprocessing


def test_preprocess_resizes_longest_side_normalises_and_pads():
    assert preprocess_shape(240, 320, 1024) == (768, 1024)
    assert preprocess_shape(320, 240, 1024) == (1024, 768)
    assert preprocess_shape(100, 333, 1024) == (308, 1024)  # 307.5 rounds up
    image = sample_image(30, 50)
    pixels, (new_h, new_w) = preprocess_image(image, 64)
    assert pixels.shape == (1, 3, 64, 64) and (new_h, new_w) == (38, 64)
    resized = Image.fromarray(np.rint(image * 255).astype(np.uint8)).resize(
        (64, 38), Image.BILINEAR
    )
    expected = (np.asarray(resized, dtype=np.float32) - PIXEL_MEAN) / PIXEL_STD
    np.testing.assert_allclose(pixels[0].permute(1, 2, 0).numpy()[:38], expected, atol=1e-5)
    assert (pixels[0, :, 38:, :] == 0).all()


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


# --------------------------------------------------------------- loading and decoding


def test_missing_model_error_names_the_model(tmp_path, monkeypatch):
    models = pytest.importorskip("vprflow.models.hub", reason="vprflow.models.hub not written yet")
    from vprflow.models.sam.adapters import load_sam

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    missing = tmp_path / "no-such-sam"
    with pytest.raises(models.ModelNotFoundError, match="no-such-sam"):
        load_sam({"model": str(missing)}, device="cpu")
    with pytest.raises(models.ModelNotFoundError, match="nobody/sam-vit-missing"):
        load_sam({"model": "nobody/sam-vit-missing", "cache_dir": str(tmp_path)}, device="cpu")


def test_loaded_with_sdpa_attention(sam_kind_model):
    kind, path, _ = sam_kind_model
    assert _load(kind, path).adapter.model.config._attn_implementation == "sdpa"


def test_the_one_sam_loader_builds_the_kind_its_entry_names(sam_kind_model):
    # One loader serves every SAM kind: the entry's `segmenter` picks the model class,
    # the adapter and the adapter's options (SAM-HQ's hq_token_only).
    kind, path, _ = sam_kind_model
    extra = {"hq_token_only": True} if kind == "sam_hq" else {}
    entry = {"segmenter": kind, "model": str(path), "points_per_side": SIDE, **extra}
    segmenter = load_model("segments", entry, "cpu")
    class_name, adapter_class = SAM_KINDS[kind]
    assert type(segmenter.adapter) is adapter_class
    assert type(segmenter.adapter.model).__name__ == class_name
    if kind == "sam_hq":
        assert segmenter.adapter.hq_token_only is True


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


def test_adapter_decode_equals_a_direct_model_call(sam_kind_model):
    kind, path, model = sam_kind_model
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
