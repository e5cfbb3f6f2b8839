"""Tiny randomly initialised DINOv2, DINO and SAM checkpoints, saved like real ones.

No weights can be downloaded here; these exercise the real loaders end to end.
"""

from __future__ import annotations

from pathlib import Path

import torch
from transformers import Dinov2Config, Dinov2Model, SamConfig, SamModel, ViTConfig, ViTModel


def _randomise(model: torch.nn.Module, seed: int, scale: float = 1.0) -> torch.nn.Module:
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, parameter in model.named_parameters():
            if "norm" in name:  # LayerNorms near identity keep activations finite
                continue
            parameter.copy_(torch.randn(parameter.shape, generator=generator) * scale)
    return model.eval()


def save_tiny_dinov2(path: Path, seed: int = 0) -> Path:
    config = Dinov2Config(
        hidden_size=32, num_hidden_layers=3, num_attention_heads=2, mlp_ratio=2, patch_size=14
    )
    _randomise(Dinov2Model(config), seed, 0.2).save_pretrained(path)
    return path


def save_tiny_dino(path: Path, seed: int = 0) -> Path:
    config = ViTConfig(
        hidden_size=32,
        num_hidden_layers=2,
        num_attention_heads=2,
        intermediate_size=64,
        patch_size=8,
        image_size=224,
    )
    _randomise(ViTModel(config, add_pooling_layer=False), seed, 0.2).save_pretrained(path)
    return path


def save_tiny_sam(path: Path, seed: int = 0, model_size: int = 64) -> Path:
    hidden = 32
    config = SamConfig(
        vision_config={
            "hidden_size": hidden,
            "output_channels": hidden,
            "num_hidden_layers": 2,
            "num_attention_heads": 2,
            "image_size": model_size,
            "patch_size": 16,
            "window_size": 4,
            "global_attn_indexes": [1],
            "num_pos_feats": hidden // 2,
            "mlp_dim": 64,
        },
        prompt_encoder_config={
            "hidden_size": hidden,
            "image_size": model_size,
            "patch_size": 16,
            "mask_input_channels": 8,
        },
        mask_decoder_config={
            "hidden_size": hidden,
            "mlp_dim": 64,
            "num_hidden_layers": 2,
            "num_attention_heads": 2,
            "iou_head_hidden_dim": 32,
        },
    )
    _randomise(SamModel(config), seed).save_pretrained(path)
    return path
