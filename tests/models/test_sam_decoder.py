"""The shared-image mask decoder (``vprflow.models.sam.decoder``) against direct formulas.

Reference for SAM and SAM 2: transformers' own mask decoder module, called as the model
calls it (image embedding repeated per prompt). Reference for SAM-HQ: the original
library's ``MaskDecoderHQ`` (SysCV/sam-hq, multimask output) written out below with
the transformers submodules, because transformers' ``SamHQMaskDecoder`` upscales the
image embedding from *before* its two-way transformer where the original upscales the
transformer's output (checked here too, so the day transformers changes it shows).

In float64 the re-associated products must agree to ~1e-12 of the logits' scale (same
function, different summation order); float32 to ~1e-4. Decoders are built at the
published size (256 channels, 8 heads) with random weights, on a non-square grid so that
a swapped height and width cannot pass.
"""

from __future__ import annotations

import pytest
import torch
from transformers.models.sam.configuration_sam import SamMaskDecoderConfig
from transformers.models.sam.modeling_sam import SamMaskDecoder
from transformers.models.sam2.configuration_sam2 import Sam2MaskDecoderConfig
from transformers.models.sam2.modeling_sam2 import Sam2MaskDecoder
from transformers.models.sam_hq.configuration_sam_hq import SamHQMaskDecoderConfig
from transformers.models.sam_hq.modeling_sam_hq import SamHQMaskDecoder

from vprflow.models.sam import decoder as sam_decoder

GRID = (6, 10)  # low-res image embedding h x w (64 x 64 for the published models)
PROMPTS = 5
SPARSE = 2  # tokens per point prompt (the point and transformers' padding point)
VIT_DIM = 48


def _decoder(kind: str, dtype: torch.dtype):
    torch.manual_seed({"sam": 0, "sam2": 1, "sam_hq": 2}[kind])
    if kind == "sam":
        config, build = SamMaskDecoderConfig(), SamMaskDecoder
    elif kind == "sam2":
        config, build = Sam2MaskDecoderConfig(), Sam2MaskDecoder
    else:
        config, build = SamHQMaskDecoderConfig(vit_dim=VIT_DIM), SamHQMaskDecoder
    config._attn_implementation = "sdpa"  # as the loader asks for
    decoder = build(config)
    # Default init leaves logits near 0.03; larger weights give logits of order 1 and
    # attention far from uniform, so a mistake in any product shows.
    with torch.no_grad():
        for name, parameter in decoder.named_parameters():
            if name.endswith("weight") and parameter.dim() >= 2:
                parameter.mul_(2.0)
    return decoder.to(dtype).eval()


def _inputs(kind: str, dtype: torch.dtype, channels: int = 256):
    generator = torch.Generator().manual_seed(7)

    def rand(*shape):
        return torch.randn(*shape, generator=generator, dtype=torch.float64).to(dtype)

    h, w = GRID
    inputs = {
        "embedding": rand(1, channels, h, w),
        "image_pe": rand(1, channels, h, w),
        "sparse": rand(1, PROMPTS, SPARSE, channels),
        "dense": rand(1, channels, h, w) * 0.1,
    }
    if kind == "sam2":
        inputs["high_res"] = [
            rand(1, channels // 8, 4 * h, 4 * w),
            rand(1, channels // 4, 2 * h, 2 * w),
        ]
    if kind == "sam_hq":
        inputs["intermediate"] = [rand(1, h, w, VIT_DIM)]
    return inputs


def _shared(kind, decoder, x, hq_token_only=False, chunk=None):
    common = {"image_pe": x["image_pe"], "sparse": x["sparse"], "dense": x["dense"]}
    common["chunk"] = chunk
    with torch.no_grad():
        if kind == "sam":
            return sam_decoder.decode_sam(decoder, x["embedding"], **common)
        if kind == "sam2":
            return sam_decoder.decode_sam2(decoder, [*x["high_res"], x["embedding"]], **common)
        return sam_decoder.decode_sam_hq(
            decoder, x["embedding"], x["intermediate"], hq_token_only=hq_token_only, **common
        )


def _transformers(kind, decoder, x):
    """transformers' decoder module -> logits [P, 3, 4h, 4w], IoUs [P, 3]."""
    arguments = {
        "image_embeddings": x["embedding"],
        "image_positional_embeddings": x["image_pe"],
        "sparse_prompt_embeddings": x["sparse"],
        "dense_prompt_embeddings": x["dense"],
        "multimask_output": True,
    }
    with torch.no_grad():
        if kind == "sam2":
            masks, iou, _, _ = decoder(**arguments, high_resolution_features=x["high_res"])
        else:
            masks, iou = decoder(**arguments)
    return masks[0], iou[0]


def hq_original(decoder, x, hq_token_only):
    """SysCV/sam-hq ``MaskDecoderHQ.forward`` + ``predict_masks``, multimask output ->
    (the best SAM mask + the HQ mask, or the HQ mask alone) [P, 1, 4h, 4w], IoU [P, 1]."""
    act = decoder.activation
    embedding, dense, image_pe, sparse = x["embedding"], x["dense"], x["image_pe"], x["sparse"]
    vit = x["intermediate"][0].permute(0, 3, 1, 2)
    hq_features = decoder.encoder_conv2(act(decoder.encoder_norm(decoder.encoder_conv1(embedding))))
    hq_features = hq_features + decoder.compress_vit_conv2(
        act(decoder.compress_vit_norm(decoder.compress_vit_conv1(vit)))
    )
    prompts = sparse.shape[1]
    output = torch.cat(
        [decoder.iou_token.weight, decoder.mask_tokens.weight, decoder.hq_token.weight]
    )
    tokens = torch.cat([output.expand(1, prompts, -1, -1), sparse], dim=2)
    src = (embedding + dense).repeat_interleave(prompts, 0)
    pos = image_pe.repeat_interleave(prompts, 0)
    hs, keys = decoder.transformer(
        point_embeddings=tokens,
        image_embeddings=src,
        image_positional_embeddings=pos,
        attention_similarity=None,
    )
    hs = hs[0]
    channels, h, w = embedding.shape[1:]
    src = keys[:, 0].transpose(1, 2).reshape(prompts, channels, h, w)  # the transformer's output
    upscaled = act(
        decoder.upscale_conv2(act(decoder.upscale_layer_norm(decoder.upscale_conv1(src))))
    )
    upscaled_hq = decoder.mask_conv2(act(decoder.mask_norm(decoder.mask_conv1(upscaled))))
    upscaled_hq = upscaled_hq + hq_features
    hyper = [decoder.output_hypernetworks_mlps[i](hs[:, 1 + i]) for i in range(4)]
    masks_sam = torch.einsum("pmc,pchw->pmhw", torch.stack(hyper, 1), upscaled)
    masks_hq = torch.einsum("pc,pchw->phw", decoder.hq_mask_mlp(hs[:, 5]), upscaled_hq)[:, None]
    iou, best = decoder.iou_prediction_head(hs[:, 0])[:, 1:4].max(dim=1)
    best_sam = masks_sam[:, 1:4][torch.arange(prompts), best][:, None]
    return (masks_hq if hq_token_only else best_sam + masks_hq), iou[:, None]


def _reference(kind, decoder, x, hq_token_only=False):
    if kind == "sam_hq":
        with torch.no_grad():
            return hq_original(decoder, x, hq_token_only)
    return _transformers(kind, decoder, x)


@pytest.mark.parametrize("chunk", [None, 2])  # 2: chunks of 2, 2 and 1 prompts
@pytest.mark.parametrize("kind", ["sam", "sam2", "sam_hq"])
def test_float64_equals_the_direct_decoder(kind, chunk):
    decoder = _decoder(kind, torch.float64)
    x = _inputs(kind, torch.float64)
    for hq_token_only in [False, True] if kind == "sam_hq" else [False]:
        logits, iou = _shared(kind, decoder, x, hq_token_only, chunk)
        expected_logits, expected_iou = _reference(kind, decoder, x, hq_token_only)
        per_point = 1 if kind == "sam_hq" else 3
        h, w = GRID
        assert logits.shape == expected_logits.shape == (PROMPTS, per_point, 4 * h, 4 * w)
        assert iou.shape == expected_iou.shape == (PROMPTS, per_point)
        scale = expected_logits.abs().max()
        assert scale > 0.5, "logits degenerate"
        # Same function, summed in another order: float64 rounding only.
        torch.testing.assert_close(logits, expected_logits, atol=1e-11 * scale, rtol=0)
        torch.testing.assert_close(iou, expected_iou, atol=1e-11, rtol=0)


@pytest.mark.parametrize("kind", ["sam", "sam2", "sam_hq"])
def test_float32_within_rounding_of_float64(kind):
    reference = _reference(kind, _decoder(kind, torch.float64), _inputs(kind, torch.float64))
    logits, iou = _shared(kind, _decoder(kind, torch.float32), _inputs(kind, torch.float32))
    scale = reference[0].abs().max()
    # float32 through ~10 chained products and layer norms of 256 channels.
    torch.testing.assert_close(logits.double(), reference[0], atol=1e-4 * scale, rtol=0)
    torch.testing.assert_close(iou.double(), reference[1], atol=1e-4, rtol=0)


def test_transformers_sam_hq_upscales_the_embedding_before_the_transformer():
    """Why SAM-HQ is checked against the original, not transformers: their HQ decoder's
    masks differ from the original's (if this starts failing, transformers was fixed and
    the adapter's ``shared_decoder=False`` path becomes a valid reference again)."""
    decoder = _decoder("sam_hq", torch.float64)
    x = _inputs("sam_hq", torch.float64)
    original, _ = hq_original(decoder, x, hq_token_only=True)
    with torch.no_grad():
        masks, _ = decoder(
            image_embeddings=x["embedding"],
            image_positional_embeddings=x["image_pe"],
            sparse_prompt_embeddings=x["sparse"],
            dense_prompt_embeddings=x["dense"],
            multimask_output=True,
            hq_token_only=True,
            intermediate_embeddings=x["intermediate"],
        )
    assert (masks[0] - original).abs().max() > 1e-3 * original.abs().max()


def test_blocked_layout_round_trip():
    generator = torch.Generator().manual_seed(0)
    h, w = GRID
    image = torch.randn(5, 4 * h, 4 * w, generator=generator)
    blocked = sam_decoder.blocked(image, 2)
    assert blocked.shape == (h * w, 16, 5)
    torch.testing.assert_close(sam_decoder.unblocked(blocked[None], h, w)[0], image, rtol=0, atol=0)
    last = sam_decoder.unblocked(blocked[None], h, w, channels_last=True)
    assert last.is_contiguous(memory_format=torch.channels_last)
    torch.testing.assert_close(last[0], image, rtol=0, atol=0)
    # One level: pixel (2y + i, 2x + j) is sub-pixel 2i + j of low-res pixel y*w + x.
    half = torch.randn(3, 2 * h, 2 * w, generator=generator)
    one = sam_decoder.blocked(half, 1)
    y, x, i, j = 4, 7, 1, 0
    torch.testing.assert_close(one[y * w + x, 2 * i + j], half[:, 2 * y + i, 2 * x + j])


def test_rejects_a_batch_of_images():
    decoder = _decoder("sam", torch.float32)
    x = _inputs("sam", torch.float32)
    with pytest.raises(ValueError, match="one image at a time"):
        sam_decoder.decode_sam(
            decoder, x["embedding"].repeat(2, 1, 1, 1), x["image_pe"], x["sparse"], x["dense"]
        )
