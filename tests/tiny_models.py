"""Tiny randomly initialised DINOv2, DINOv3, DINO, SAM, SAM-HQ and SAM 2 checkpoints,
saved like real ones.

No weights can be downloaded here; these exercise the real loaders end to end.
``tiny_vit`` (DINOv2, DINOv2 with registers, DINOv3, DINO), ``tiny_sam``, ``tiny_sam_hq``
and ``tiny_sam2`` return the model;
the ``save_tiny_*`` wrappers save it to ``path`` and return the path. Every size is a
keyword, so ``tiny_vit`` also makes the real-size architectures that
``benchmarks/bench_backbones.py`` times.

Weights: ``scale=None`` keeps the transformers initialisation (seeded with
``torch.manual_seed(seed)``); otherwise every parameter is re-drawn from
``N(0, scale**2)`` with its own generator, skipping LayerNorms (``skip_norms``) and
adding ``bias_offset`` to 1-D parameters (biases and norm weights).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import torch
from transformers import (
    Dinov2Config,
    Dinov2Model,
    Dinov2WithRegistersConfig,
    Dinov2WithRegistersModel,
    DINOv3ViTConfig,
    DINOv3ViTModel,
    Sam2Config,
    Sam2Model,
    SamConfig,
    SamHQConfig,
    SamHQModel,
    SamModel,
    ViTConfig,
    ViTModel,
)


def _randomise(
    model: torch.nn.Module,
    seed: int,
    scale: float = 1.0,
    *,
    skip_norms: bool = True,
    bias_offset: float = 0.0,
) -> torch.nn.Module:
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, parameter in model.named_parameters():
            if skip_norms and "norm" in name:  # LayerNorms near identity keep activations finite
                continue
            noise = torch.randn(parameter.shape, generator=generator) * scale
            if parameter.ndim == 1 and bias_offset:
                noise = noise + bias_offset
            parameter.copy_(noise)
    return model.eval()


def _initialise(
    build: Callable[[], torch.nn.Module], seed: int, scale: float | None, **randomise: Any
) -> torch.nn.Module:
    """``build()`` with transformers' seeded initialisation or re-drawn weights."""
    if scale is None:
        torch.manual_seed(seed)
        return build().eval()
    return _randomise(build(), seed, scale, **randomise)


# kind: (layers, patch side) of the tiny default
_TINY_VIT = {"dinov2": (3, 14), "dinov3": (3, 16), "dino": (2, 8)}


def tiny_vit(
    kind: str = "dinov2",
    *,
    hidden_size: int = 32,
    num_layers: int | None = None,
    num_heads: int = 2,
    mlp_ratio: int = 2,
    patch_size: int | None = None,
    image_size: int = 224,
    registers: int = 0,
    seed: int = 0,
    scale: float | None = 0.2,
    skip_norms: bool = True,
    bias_offset: float = 0.0,
    **config: Any,
) -> torch.nn.Module:
    """A ``kind="dinov2"`` model (DINOv2-with-registers if ``registers > 0``), a
    ``kind="dinov3"`` one (``registers`` register tokens, MLP ``mlp_ratio * hidden_size``
    wide, RoPE) or a ``kind="dino"`` one (a ViT without pooler, MLP as DINOv3's).

    ``num_layers`` and ``patch_size`` default to 3 and 14 (DINOv2), 3 and 16 (DINOv3) or
    2 and 8 (DINO);
    ``config`` holds further config keys (e.g. ``use_swiglu_ffn``).
    """
    layers, patch = _TINY_VIT[kind]
    if registers and kind == "dino":
        raise ValueError("register tokens need kind='dinov2' or 'dinov3', not 'dino'")
    config.update(
        hidden_size=hidden_size,
        num_hidden_layers=num_layers or layers,
        num_attention_heads=num_heads,
        patch_size=patch_size or patch,
        image_size=image_size,
    )
    if kind == "dino":
        vit = ViTConfig(intermediate_size=mlp_ratio * hidden_size, **config)
        build = partial(ViTModel, vit, add_pooling_layer=False)
    elif kind == "dinov3":
        vit = DINOv3ViTConfig(
            intermediate_size=mlp_ratio * hidden_size, num_register_tokens=registers, **config
        )
        build = partial(DINOv3ViTModel, vit)
    elif registers:
        vit = Dinov2WithRegistersConfig(
            mlp_ratio=mlp_ratio, num_register_tokens=registers, **config
        )
        build = partial(Dinov2WithRegistersModel, vit)
    else:
        build = partial(Dinov2Model, Dinov2Config(mlp_ratio=mlp_ratio, **config))
    return _initialise(build, seed, scale, skip_norms=skip_norms, bias_offset=bias_offset)


def _tiny_sam_configs(hidden_size: int, model_size: int) -> dict:
    """Vision / prompt encoder / mask decoder configs shared by SAM and SAM-HQ."""
    return {
        "vision_config": {
            "hidden_size": hidden_size,
            "output_channels": hidden_size,
            "num_hidden_layers": 2,
            "num_attention_heads": 2,
            "image_size": model_size,
            "patch_size": 16,
            "window_size": 4,
            "global_attn_indexes": [1],
            "num_pos_feats": hidden_size // 2,
            "mlp_dim": 64,
        },
        "prompt_encoder_config": {
            "hidden_size": hidden_size,
            "image_size": model_size,
            "patch_size": 16,
            "mask_input_channels": 8,
        },
        "mask_decoder_config": {
            "hidden_size": hidden_size,
            "mlp_dim": 64,
            "num_hidden_layers": 2,
            "num_attention_heads": 2,
            "iou_head_hidden_dim": 32,
        },
    }


def tiny_sam(
    *,
    hidden_size: int = 32,
    model_size: int = 64,
    seed: int = 0,
    scale: float | None = 1.0,
) -> SamModel:
    """A SAM model whose input side is ``model_size`` (1024 for real checkpoints)."""
    config = SamConfig(**_tiny_sam_configs(hidden_size, model_size))
    return _initialise(partial(SamModel, config), seed, scale)


def tiny_sam_hq(
    *,
    hidden_size: int = 32,
    model_size: int = 64,
    seed: int = 0,
    scale: float | None = 1.0,
) -> SamHQModel:
    """A SAM-HQ model (SAM's tiny architecture plus the HQ decoder) of input side
    ``model_size``; the HQ decoder fuses the block-0 global-attention features."""
    configs = _tiny_sam_configs(hidden_size, model_size)
    configs["vision_config"]["global_attn_indexes"] = [0, 1]
    configs["mask_decoder_config"]["vit_dim"] = hidden_size
    return _initialise(partial(SamHQModel, SamHQConfig(**configs)), seed, scale)


def tiny_sam2(
    *,
    hidden_size: int = 32,
    model_size: int = 64,
    seed: int = 0,
    scale: float | None = 1.0,
) -> Sam2Model:
    """A SAM 2 model with a 4-stage Hiera of 5 blocks (the fourth global) and input side
    ``model_size`` (a multiple of 32; 1024 for real checkpoints)."""
    if model_size % 32:
        raise ValueError(f"model_size must be a multiple of 32, got {model_size}")
    backbone = {
        "model_type": "sam2_hiera_det_model",
        "hidden_size": 16,
        "num_attention_heads": 1,
        "image_size": [model_size, model_size],
        "blocks_per_stage": [1, 1, 2, 1],
        "embed_dim_per_stage": [16, 32, 64, 128],
        "num_attention_heads_per_stage": [1, 1, 2, 2],
        "window_size_per_stage": [4, 4, 4, 2],
        "global_attention_blocks": [3],
        "window_positional_embedding_background_size": [2, 2],
    }
    config = Sam2Config(
        vision_config={
            "backbone_config": backbone,
            "backbone_channel_list": [128, 64, 32, 16],
            "backbone_feature_sizes": [[model_size // s] * 2 for s in (4, 8, 16)],
            "fpn_hidden_size": hidden_size,
        },
        prompt_encoder_config={
            "hidden_size": hidden_size,
            "image_size": model_size,
            "patch_size": 16,
            "mask_input_channels": 8,
        },
        mask_decoder_config={
            "hidden_size": hidden_size,
            "mlp_dim": 64,
            "num_hidden_layers": 2,
            "num_attention_heads": 2,
            "iou_head_hidden_dim": 32,
        },
    )
    return _initialise(partial(Sam2Model, config), seed, scale)


def save_tiny_dinov2(path: Path, **kwargs: Any) -> Path:
    tiny_vit("dinov2", **kwargs).save_pretrained(path)
    return path


def save_tiny_dinov3(path: Path, **kwargs: Any) -> Path:
    tiny_vit("dinov3", **kwargs).save_pretrained(path)
    return path


def save_tiny_dino(path: Path, **kwargs: Any) -> Path:
    tiny_vit("dino", **kwargs).save_pretrained(path)
    return path


def save_tiny_sam(path: Path, **kwargs: Any) -> Path:
    tiny_sam(**kwargs).save_pretrained(path)
    return path


def save_tiny_sam_hq(path: Path, **kwargs: Any) -> Path:
    tiny_sam_hq(**kwargs).save_pretrained(path)
    return path


def save_tiny_sam2(path: Path, **kwargs: Any) -> Path:
    tiny_sam2(**kwargs).save_pretrained(path)
    return path
