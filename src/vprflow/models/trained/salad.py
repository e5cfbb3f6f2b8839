"""SALAD (Izquierdo & Civera, CVPR 2024; github.com/serizba/salad): DINOv2-B/14 tokens
aggregated by optimal transport, 8448-d at 322 x 322.

Architecture (the published ``dinov2_salad`` model, plain torch here):

1. backbone: DINOv2 ViT-B/14 (vprflow's transformers ``Dinov2Model``, run block by block,
   position embeddings interpolated as the original facebookresearch/dinov2 code does:
   :func:`vprflow.models.vit._set_pos_embed_interpolation`), all 12 blocks then the final
   LayerNorm; the CLS token ``t`` ``[B, 768]`` and the patch tokens as a map
   ``x`` ``[B, 768, H/14, W/14]``;
2. aggregator (:class:`SaladAggregator`, ``m = 64`` clusters of ``l = 128`` dims, a
   ``g = 256`` global token): ``f = cluster_features(x)`` ``[B, l, n]`` and scores
   ``S = score(x)`` ``[B, m, n]`` (1x1-conv MLPs 768 -> 512 -> ReLU -> l / m),
   ``g = token_features(t)`` (768 -> 512 -> ReLU -> 256); ``S`` gains a dustbin row of
   the learned scalar ``dust_bin`` and 3 log-domain Sinkhorn iterations
   (:func:`sinkhorn_log`) give the transport plan ``P`` ``[B, m + 1, n]``, whose dustbin
   row is dropped; ``V[:, c, k] = sum_i f[:, c, i] P[:, k, i]``, each cluster ``V[:, :, k]``
   L2-normalised over ``c``, flattened as ``c * m + k``; the descriptor is
   ``L2([L2(g), V])`` of length ``g + l * m = 8448``.

Input: RGB in [0, 1] resized to 322 x 322 (bilinear, the SALAD evaluation) and
normalised with ImageNet's mean / std; any size that is a multiple of 14 runs.

Checkpoint: ``dino_salad.ckpt`` (github.com/serizba/salad/releases/download/v1.0.0),
a plain state dict read with ``torch.load(weights_only=True)``: ``backbone.model.<name>``
in the torch-hub DINOv2 layout (:mod:`vprflow.models.checkpoints`) and ``aggregator.*``
(``token_features.{0,2}``, ``cluster_features.{0,3}``, ``score.{0,3}``, ``dust_bin``);
keys under ``loss_fn.`` / ``miner.`` (the training module's loss, no descriptor
weights) are ignored, any other key is an error.

This module also holds the DINOv2 pieces that MegaLoc and BoQ-DINOv2 share:
:func:`dinov2_config`, :class:`DinoV2Tokens`, :func:`dinov2_hub_state_dict` (the inverse
of the checkpoint mapping, for writing test checkpoints), :func:`read_state_dict` and
:func:`load_backbone_and_head`.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
from torch import nn
from torch.nn import functional as F

from vprflow.models.checkpoints import (
    CheckpointError,
    backbone_state_dict,
    hub_to_transformers,
    read_checkpoint,
)
from vprflow.models.vit import IMAGENET_MEAN, IMAGENET_STD, _set_pos_embed_interpolation

INPUT_SIZE = (322, 322)
MEAN, STD = IMAGENET_MEAN, IMAGENET_STD
SALAD_URL = "https://github.com/serizba/salad/releases/download/v1.0.0/dino_salad.ckpt"
SALAD_FILE = "dino_salad.ckpt"
SINKHORN_ITERATIONS = 3
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
    from transformers import Dinov2Config

    return Dinov2Config(**{**VITB14, **overrides})


class DinoV2Tokens(nn.Module):
    """DINOv2 as the VPR models call it: ``[B, 3, H, W]`` (H, W multiples of the patch)
    -> ``(patches [B, C, H/p, W/p], cls [B, C])``, after the final LayerNorm when
    ``final_norm`` (SALAD, MegaLoc) and straight from the last block otherwise (BoQ).
    """

    def __init__(self, config=None, final_norm: bool = True):
        super().__init__()
        from transformers import Dinov2Model

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


def read_state_dict(path: str, model_name: str, url: str, filename: str) -> dict:
    """The state dict in ``path``: ``safetensors`` files by name, anything else with
    ``torch.load(weights_only=True)`` (a Lightning ``state_dict`` is unwrapped)."""
    hint = f"download {filename} from {url}"
    if not Path(path).is_file():
        raise CheckpointError(f"{model_name}: checkpoint {path!r} does not exist; {hint}")
    if str(path).endswith(".safetensors"):
        from safetensors.torch import load_file

        try:
            return load_file(str(path))
        except Exception as error:  # safetensors raises its own error types
            raise CheckpointError(
                f"{model_name}: checkpoint {path!r}: cannot read it as safetensors "
                f"({type(error).__name__}: {error}); {hint}"
            ) from error
    try:
        checkpoint = read_checkpoint(str(path))
    except CheckpointError as error:
        raise CheckpointError(f"{model_name}: {error}; {hint}") from error
    if isinstance(checkpoint, dict) and isinstance(checkpoint.get("state_dict"), dict):
        checkpoint = checkpoint["state_dict"]
    if not isinstance(checkpoint, dict):
        raise CheckpointError(
            f"{model_name}: checkpoint {path!r} holds a {type(checkpoint).__name__}, "
            f"not a state dict; {hint}"
        )
    return checkpoint


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


def sinkhorn_log(scores: torch.Tensor, dust_bin: torch.Tensor, iterations: int) -> torch.Tensor:
    """Log transport plan ``[B, m + 1, n]`` of ``scores`` ``[B, m, n]`` plus a dustbin row.

    Source marginals (rows): ``1 / (n + m)`` per cluster and ``(n - m) / (n + m)`` for the
    dustbin; target marginals (columns): ``1 / (n + m)``. Starting from zero potentials,
    each iteration sets ``u = log a - logsumexp_j(S + v)`` then
    ``v = log b - logsumexp_i(S + u)``; the result is ``S + u + v + log(n + m)``: the
    plan scaled by ``n + m`` so that every patch (column) spreads a mass of exactly 1
    over the clusters and the dustbin, the scale SALAD was trained with.
    """
    batch, m, n = scores.shape
    augmented = torch.cat([scores, dust_bin.to(scores.dtype).expand(batch, 1, n)], dim=1)
    log_norm = -math.log(n + m)
    log_a = torch.full((batch, m + 1), log_norm, dtype=scores.dtype, device=scores.device)
    log_a[:, -1] += math.log(n - m)
    log_b = torch.full((batch, n), log_norm, dtype=scores.dtype, device=scores.device)
    u, v = torch.zeros_like(log_a), torch.zeros_like(log_b)
    for _ in range(iterations):
        u = log_a - torch.logsumexp(augmented + v.unsqueeze(1), dim=2)
        v = log_b - torch.logsumexp(augmented + u.unsqueeze(2), dim=1)
    return augmented + u.unsqueeze(2) + v.unsqueeze(1) - log_norm


class SaladAggregator(nn.Module):
    """SALAD's optimal-transport aggregation (module docstring, step 2):
    ``(x [B, C, h, w], t [B, C])`` -> ``[B, token_dim + cluster_dim * num_clusters]``.
    Submodule indices are SALAD's (dropout slots at index 1 hold no weights)."""

    def __init__(
        self,
        num_channels: int = 768,
        num_clusters: int = 64,
        cluster_dim: int = 128,
        token_dim: int = 256,
        mlp_dim: int = 512,
    ):
        super().__init__()
        self.num_clusters, self.cluster_dim, self.token_dim = num_clusters, cluster_dim, token_dim
        self.token_features = nn.Sequential(
            nn.Linear(num_channels, mlp_dim), nn.ReLU(), nn.Linear(mlp_dim, token_dim)
        )
        self.cluster_features = nn.Sequential(
            nn.Conv2d(num_channels, mlp_dim, 1),
            nn.Identity(),
            nn.ReLU(),
            nn.Conv2d(mlp_dim, cluster_dim, 1),
        )
        self.score = nn.Sequential(
            nn.Conv2d(num_channels, mlp_dim, 1),
            nn.Identity(),
            nn.ReLU(),
            nn.Conv2d(mlp_dim, num_clusters, 1),
        )
        self.dust_bin = nn.Parameter(torch.tensor(1.0))
        self.dim = token_dim + cluster_dim * num_clusters

    def forward(self, x: torch.Tensor, token: torch.Tensor) -> torch.Tensor:
        features = self.cluster_features(x).flatten(2)  # [B, l, n]
        scores = self.score(x).flatten(2)  # [B, m, n]
        plan = sinkhorn_log(scores, self.dust_bin, SINKHORN_ITERATIONS).exp()[:, :-1]
        clusters = torch.einsum("bln,bmn->blm", features, plan)
        clusters = F.normalize(clusters, p=2, dim=1).flatten(1)
        scene = F.normalize(self.token_features(token), p=2, dim=-1)
        return F.normalize(torch.cat([scene, clusters], dim=-1), p=2, dim=-1)


class SALAD(nn.Module):
    """DINOv2 + :class:`SaladAggregator`. ``forward``: ImageNet-normalised
    ``[B, 3, H, W]`` (multiples of 14; 322 x 322 published) -> ``[B, 8448]``;
    ``feature_map``: the same input -> normed patch tokens ``[B, 768, H/14, W/14]``."""

    def __init__(self, config=None, *, num_clusters: int = 64, cluster_dim: int = 128):
        super().__init__()
        self.backbone = DinoV2Tokens(config, final_norm=True)
        self.aggregator = SaladAggregator(
            self.backbone.dim, num_clusters=num_clusters, cluster_dim=cluster_dim
        )
        self.dim = self.aggregator.dim
        self.input_size, self.mean, self.std = INPUT_SIZE, MEAN, STD

    def feature_map(self, images: torch.Tensor) -> torch.Tensor:
        return self.backbone(images)[0]

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.aggregator(*self.backbone(images))


def load_salad(path: str, config=None, *, num_clusters: int = 64, cluster_dim: int = 128) -> SALAD:
    """SALAD with the weights of ``path`` (``dino_salad.ckpt`` layout, module docstring).
    ``config`` replaces ViT-B/14 (tests). Raises :class:`CheckpointError` naming the
    file, the key at fault and :data:`SALAD_URL`."""
    model = SALAD(config, num_clusters=num_clusters, cluster_dim=cluster_dim)
    state = read_state_dict(path, "SALAD", SALAD_URL, SALAD_FILE)
    load_backbone_and_head(
        model.backbone,
        model.aggregator,
        state,
        path,
        model_name="SALAD",
        backbone_prefixes=("backbone.model.",),
        head_prefix="aggregator.",
        hint=f"expected {SALAD_FILE} from {SALAD_URL}",
        # SALAD's Lightning module also holds its training loss and miner, which carry
        # no weights of the descriptor.
        ignored_prefixes=("loss_fn.", "miner."),
    )
    return model.eval()
