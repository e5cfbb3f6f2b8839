"""DINOv2 ViT-B/14 as the trained VPR models call it (SALAD, BoQ-DINOv2, VLAD-BuFF,
MegaLoc): :func:`dinov2_config`, :class:`DinoV2Tokens` (the patch tokens as a map and
the CLS token), :func:`dinov2_hub_state_dict` (the inverse of the checkpoint mapping,
for writing test checkpoints) and :func:`load_backbone_and_head` (a torch-hub-named
DINOv2 and the model's head from one state dict).

The backbone is vprflow's transformers ``Dinov2Model``, run block by block, position
embeddings interpolated as the original facebookresearch/dinov2 code does
(:func:`vprflow.models.vit._set_pos_embed_interpolation`); the published checkpoints
store it in the torch-hub layout (:mod:`vprflow.models.checkpoints`).
"""

from __future__ import annotations

import torch
from torch import nn
from transformers import Dinov2Config, Dinov2Model

from vprflow.models.checkpoints import CheckpointError, backbone_state_dict, hub_to_transformers
from vprflow.models.vit import _set_pos_embed_interpolation

# The torch-hub ViT-B/14 (dinov2_vitb14): 518-pixel pretraining grid of 37 x 37.
VITB14 = {
    "hidden_size": 768,
    "num_hidden_layers": 12,
    "num_attention_heads": 12,
    "mlp_ratio": 4,
    "patch_size": 14,
    "image_size": 518,
    "layerscale_value": 1.0,
    "layer_norm_eps": 1e-6,
    "use_swiglu_ffn": False,
    "qkv_bias": True,
    "hidden_act": "gelu",
}


def dinov2_config(**overrides):
    """A transformers ``Dinov2Config`` of the torch-hub ViT-B/14, ``overrides`` applied
    (tests: ``hidden_size=32, num_hidden_layers=2, num_attention_heads=2``...)."""
    return Dinov2Config(**{**VITB14, **overrides})


class DinoV2Tokens(nn.Module):
    """DINOv2 as the VPR models call it: ``[B, 3, H, W]`` (H, W multiples of the patch)
    -> ``(patches [B, C, H/p, W/p], cls [B, C])``, after the final LayerNorm when
    ``final_norm`` (SALAD, MegaLoc) and straight from the last block otherwise (BoQ).
    """

    def __init__(self, config=None, final_norm: bool = True):
        super().__init__()
        self.model = Dinov2Model(config or dinov2_config()).eval()
        _set_pos_embed_interpolation(self.model, "original")
        self.final_norm = final_norm
        self.patch_size = int(self.model.config.patch_size)
        self.dim = int(self.model.config.hidden_size)

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        batch, _, height, width = images.shape
        if height % self.patch_size or width % self.patch_size:
            raise ValueError(
                f"DINOv2 input {height} x {width} is not a multiple of the patch "
                f"{self.patch_size}; resize it first"
            )
        tokens = self.model.embeddings(images)
        for block in self.model.encoder.layer:
            tokens = block(tokens)
        if self.final_norm:
            tokens = self.model.layernorm(tokens)
        rows, cols = height // self.patch_size, width // self.patch_size
        patches = tokens[:, 1:].reshape(batch, rows, cols, self.dim).permute(0, 3, 1, 2)
        return patches, tokens[:, 0]


def dinov2_hub_state_dict(tokens: DinoV2Tokens) -> dict[str, torch.Tensor]:
    """``tokens``' weights under the torch-hub DINOv2 names (fused ``attn.qkv``,
    ``ls1.gamma``, ``norm``...): the layout the published checkpoints store."""
    top = {
        "embeddings.cls_token": "cls_token",
        "embeddings.position_embeddings": "pos_embed",
        "embeddings.mask_token": "mask_token",
        "embeddings.patch_embeddings.projection.weight": "patch_embed.proj.weight",
        "embeddings.patch_embeddings.projection.bias": "patch_embed.proj.bias",
        "layernorm.weight": "norm.weight",
        "layernorm.bias": "norm.bias",
    }
    renames = {"layer_scale1.lambda1": "ls1.gamma", "layer_scale2.lambda1": "ls2.gamma"}
    hub: dict[str, torch.Tensor] = {}
    qkv: dict[tuple[int, str], dict[str, torch.Tensor]] = {}
    for name, tensor in tokens.model.state_dict().items():
        if name in top:
            hub[top[name]] = tensor.clone()
            continue
        _, _, index, rest = name.split(".", 3)
        block = f"blocks.{index}."
        module, _, kind = rest.rpartition(".")
        leaf = module.rpartition(".")[2]
        if rest in renames:
            hub[block + renames[rest]] = tensor.clone()
        elif leaf in ("q_proj", "k_proj", "v_proj", "query", "key", "value"):
            qkv.setdefault((int(index), kind), {})[leaf[0]] = tensor
        elif leaf in ("o_proj", "dense"):
            hub[f"{block}attn.proj.{kind}"] = tensor.clone()
        else:  # norm1, norm2, mlp.fc1, mlp.fc2 keep their names
            hub[block + rest] = tensor.clone()
    for (index, kind), parts in qkv.items():
        hub[f"blocks.{index}.attn.qkv.{kind}"] = torch.cat([parts[c] for c in "qkv"], dim=0)
    return hub


def load_backbone_and_head(
    backbone: DinoV2Tokens,
    head: nn.Module,
    state: dict,
    path: str,
    *,
    model_name: str,
    backbone_prefixes: tuple[str, ...],
    head_prefix: str,
    hint: str,
    ignored_prefixes: tuple[str, ...] = (),
) -> None:
    """Load the torch-hub-named DINOv2 under one of ``backbone_prefixes`` into
    ``backbone`` and the ``head_prefix`` keys into ``head``; every weight of both must
    be present with its shape, and no other key may be in ``state`` (but those under
    ``ignored_prefixes``)."""
    try:
        hub, prefix = backbone_state_dict(state, path)
    except CheckpointError as error:
        raise CheckpointError(f"{model_name}: {error}; {hint}") from error
    if prefix not in backbone_prefixes:
        raise CheckpointError(
            f"{model_name}: checkpoint {path!r} keeps its DINOv2 under {prefix!r}, "
            f"expected {' or '.join(repr(p) for p in backbone_prefixes)}; {hint}"
        )
    own_backbone = backbone.model.state_dict()
    mapped, unplaced = hub_to_transformers(hub, set(own_backbone))
    head_state = {k[len(head_prefix) :]: v for k, v in state.items() if k.startswith(head_prefix)}
    own_head = head.state_dict()
    unexpected = [prefix + n for n in unplaced] + [n for n in mapped if n not in own_backbone]
    unexpected += [k for k in state if not k.startswith((prefix, head_prefix, *ignored_prefixes))]
    unexpected += [head_prefix + k for k in head_state if k not in own_head]
    # Missing weights are named as the file would name them (torch-hub names); the mask
    # token only serves masked-image pretraining, and MegaLoc's file has none.
    missing = [
        prefix + n for n in dinov2_hub_state_dict(backbone) if n not in hub and n != "mask_token"
    ]
    if not missing:
        missing = [n for n in own_backbone if n not in mapped and not n.endswith("mask_token")]
    missing += [head_prefix + k for k in own_head if k not in head_state]
    if missing or unexpected:
        raise CheckpointError(
            f"{model_name}: checkpoint {path!r} does not fit: missing keys {sorted(missing)[:6]}"
            f" ({len(missing)}), unexpected keys {sorted(unexpected)[:6]} ({len(unexpected)}); "
            + hint
        )
    shapes = [
        (prefix + n, tuple(t.shape), tuple(own_backbone[n].shape))
        for n, t in mapped.items()
        if tuple(t.shape) != tuple(own_backbone[n].shape)
    ] + [
        (head_prefix + n, tuple(t.shape), tuple(own_head[n].shape))
        for n, t in head_state.items()
        if tuple(t.shape) != tuple(own_head[n].shape)
    ]
    if shapes:
        key, found, expected = shapes[0]
        raise CheckpointError(
            f"{model_name}: checkpoint {path!r} key {key!r} has shape {found}, expected "
            f"{expected} ({len(shapes)} shapes differ); {hint}"
        )
    backbone.model.load_state_dict({k: v.float() for k, v in mapped.items()}, strict=False)
    head.load_state_dict({k: v.float() for k, v in head_state.items()})
