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

The DINOv2 it shares with BoQ-DINOv2, VLAD-BuFF and MegaLoc is
:mod:`vprflow.models.trunks.dinov2`'s; MegaLoc also reads :class:`SaladAggregator`.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from vprflow.models.kinds import IMAGENET_MEAN, IMAGENET_STD, trained_model
from vprflow.models.trunks.dinov2 import DinoV2Tokens, load_backbone_and_head
from vprflow.models.trunks.state_dicts import TRAINING_PREFIXES, read_state_dict

MEAN, STD = IMAGENET_MEAN, IMAGENET_STD
# The published file and input size (models/kinds.py's entry).
ENTRY = trained_model("salad")
INPUT_SIZE = ENTRY.height_width
SINKHORN_ITERATIONS = 3


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
    file, the key at fault and where to get the published file."""
    model = SALAD(config, num_clusters=num_clusters, cluster_dim=cluster_dim)
    published = ENTRY.published()
    state = read_state_dict(path, "SALAD", published.url, published.file)
    load_backbone_and_head(
        model.backbone,
        model.aggregator,
        state,
        path,
        model_name="SALAD",
        backbone_prefixes=("backbone.model.",),
        head_prefix="aggregator.",
        hint=published.hint,
        ignored_prefixes=TRAINING_PREFIXES,
    )
    return model.eval()
