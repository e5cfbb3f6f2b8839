"""BoQ with a DINOv2 backbone (Ali-bey et al., CVPR 2024, updated arXiv 2405.07364 §4.5;
github.com/amaralibey/Bag-of-Queries): DINOv2-B/14 patch tokens + Bag-of-Queries,
12288-d at 322 x 322.

Architecture (``get_trained_boq(backbone_name="dinov2", output_dim=12288)``, plain
torch here):

1. backbone: DINOv2 ViT-B/14, all 12 blocks *without* the final LayerNorm (BoQ's
   ``DinoV2`` wrapper never calls it), position embeddings interpolated as the original
   DINOv2 code does; the patch tokens as a map ``[B, 768, H/14, W/14]`` (CLS dropped);
2. :class:`BoQAggregator` (``proj_channels = 384``, 64 queries, 2 blocks, 6 heads,
   ``row_dim = 32``): ``proj_c`` (3x3 convolution, padding 1, 768 -> 384), flatten to
   ``[B, n, 384]``, ``norm_input`` (LayerNorm); each :class:`BoQBlock` refines the tokens
   with a post-norm transformer encoder layer (ReLU MLP of 4 x 384, no dropout,
   LayerNorm eps 1e-5) and lets its learned ``queries`` ``[1, 64, 384]``, first passed
   through self-attention with a residual and ``norm_q``, cross-attend to the refined
   tokens, then ``norm_out``: ``[B, 64, 384]``. The 2 blocks' outputs are concatenated
   over queries (``[B, 128, 384]``), ``fc`` (``Linear(128, 32)``) maps queries to rows
   per channel (``[B, 384, 32]``), flattened as ``channel * 32 + row`` and
   L2-normalised: ``[B, 12288]``.

Input: RGB in [0, 1] resized to 322 x 322 (bicubic with antialiasing, BoQ's README) and
normalised with ImageNet's mean / std.

Checkpoint: ``dinov2_12288.pth``
(github.com/amaralibey/Bag-of-Queries/releases/download/v1.0), a plain state dict read
with ``torch.load(weights_only=True)``: ``backbone.dino.<torch-hub DINOv2 name>`` and
``aggregator.*`` (``proj_c``, ``norm_input``, ``boqs.<i>.{encoder.{self_attn.in_proj_*,
self_attn.out_proj.*, linear1, linear2, norm1, norm2}, queries, self_attn.*, norm_q,
cross_attn.*, norm_out}``, ``fc``), the names of torch's ``TransformerEncoderLayer`` and
``MultiheadAttention``, whose forward is written out here.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from vprflow.models.trained.salad import (
    MEAN,
    STD,
    DinoV2Tokens,
    load_backbone_and_head,
    read_state_dict,
)

INPUT_SIZE = (322, 322)
BOQ_DINOV2_URL = (
    "https://github.com/amaralibey/Bag-of-Queries/releases/download/v1.0/dinov2_12288.pth"
)
BOQ_DINOV2_FILE = "dinov2_12288.pth"
BOQ_DINOV2_DIM = 12288


class Attention(nn.Module):
    """Multi-head attention with ``nn.MultiheadAttention``'s parameters (``in_proj_weight``
    ``[3E, E]``, ``in_proj_bias``, ``out_proj``): ``(query [B, Lq, E], memory [B, Lk, E])``
    -> ``[B, Lq, E]``, softmax over ``q k^T / sqrt(E / heads)`` per head."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.in_proj_weight = nn.Parameter(torch.zeros(3 * dim, dim))
        self.in_proj_bias = nn.Parameter(torch.zeros(3 * dim))
        self.out_proj = nn.Linear(dim, dim)

    def forward(self, query: torch.Tensor, memory: torch.Tensor) -> torch.Tensor:
        w_q, w_k, w_v = self.in_proj_weight.chunk(3)
        b_q, b_k, b_v = self.in_proj_bias.chunk(3)
        batch, length, dim = query.shape

        def heads(x: torch.Tensor) -> torch.Tensor:
            return x.reshape(batch, x.shape[1], self.heads, dim // self.heads).transpose(1, 2)

        q = heads(F.linear(query, w_q, b_q))
        k = heads(F.linear(memory, w_k, b_k))
        v = heads(F.linear(memory, w_v, b_v))
        weights = torch.softmax(q @ k.transpose(-2, -1) / (dim // self.heads) ** 0.5, dim=-1)
        out = (weights @ v).transpose(1, 2).reshape(batch, length, dim)
        return self.out_proj(out)


class EncoderLayer(nn.Module):
    """Post-norm transformer encoder layer, ReLU MLP, no dropout, LayerNorm eps 1e-5:
    ``x = norm1(x + self_attn(x)); x = norm2(x + linear2(relu(linear1(x))))``.
    ``[B, n, E]`` -> ``[B, n, E]``; names as ``nn.TransformerEncoderLayer``'s."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.self_attn = Attention(dim, heads)
        self.linear1 = nn.Linear(dim, 4 * dim)
        self.linear2 = nn.Linear(4 * dim, dim)
        self.norm1 = nn.LayerNorm(dim)
        self.norm2 = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.norm1(x + self.self_attn(x, x))
        return self.norm2(x + self.linear2(F.relu(self.linear1(x))))


class BoQBlock(nn.Module):
    """One Bag-of-Queries block: ``[B, n, E]`` -> ``(refined tokens [B, n, E],
    query outputs [B, Q, E])`` (module docstring, step 2)."""

    def __init__(self, dim: int, num_queries: int, heads: int):
        super().__init__()
        self.encoder = EncoderLayer(dim, heads)
        self.queries = nn.Parameter(torch.zeros(1, num_queries, dim))
        self.self_attn = Attention(dim, heads)
        self.norm_q = nn.LayerNorm(dim)
        self.cross_attn = Attention(dim, heads)
        self.norm_out = nn.LayerNorm(dim)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        x = self.encoder(x)
        queries = self.queries.expand(x.shape[0], -1, -1)
        queries = self.norm_q(queries + self.self_attn(queries, queries))
        return x, self.norm_out(self.cross_attn(queries, x))


class BoQAggregator(nn.Module):
    """``[B, C, h, w]`` -> ``[B, proj_channels * row_dim]`` (module docstring, step 2)."""

    def __init__(
        self,
        in_channels: int = 768,
        proj_channels: int = 384,
        num_queries: int = 64,
        num_layers: int = 2,
        row_dim: int = 32,
    ):
        super().__init__()
        self.proj_c = nn.Conv2d(in_channels, proj_channels, kernel_size=3, padding=1)
        self.norm_input = nn.LayerNorm(proj_channels)
        self.boqs = nn.ModuleList(
            BoQBlock(proj_channels, num_queries, proj_channels // 64) for _ in range(num_layers)
        )
        self.fc = nn.Linear(num_layers * num_queries, row_dim)
        self.dim = proj_channels * row_dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.norm_input(self.proj_c(x).flatten(2).transpose(1, 2))
        outputs = []
        for block in self.boqs:
            x, out = block(x)
            outputs.append(out)
        rows = self.fc(torch.cat(outputs, dim=1).transpose(1, 2))  # [B, E, row_dim]
        return F.normalize(rows.flatten(1), p=2, dim=-1)


class BoQDinoV2(nn.Module):
    """``forward``: ImageNet-normalised ``[B, 3, H, W]`` (multiples of 14; 322 x 322
    published) -> ``[B, 12288]``; ``feature_map``: the same input -> DINOv2's last-block
    patch tokens (no final norm) ``[B, 768, H/14, W/14]``."""

    def __init__(self, config=None, **aggregator):
        super().__init__()
        self.backbone = DinoV2Tokens(config, final_norm=False)
        self.aggregator = BoQAggregator(self.backbone.dim, **aggregator)
        self.dim = self.aggregator.dim
        self.input_size, self.mean, self.std = INPUT_SIZE, MEAN, STD

    def feature_map(self, images: torch.Tensor) -> torch.Tensor:
        return self.backbone(images)[0]

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.aggregator(self.backbone(images)[0])


def load_boq_dinov2(path: str, config=None, **aggregator) -> BoQDinoV2:
    """BoQ-DINOv2 with the weights of ``path`` (``dinov2_12288.pth`` layout, module
    docstring). ``config`` / ``aggregator`` replace the published sizes (tests). Raises
    :class:`~vprflow.models.checkpoints.CheckpointError` naming the file, the key at
    fault and :data:`BOQ_DINOV2_URL`."""
    model = BoQDinoV2(config, **aggregator)
    state = read_state_dict(path, "BoQ-DINOv2", BOQ_DINOV2_URL, BOQ_DINOV2_FILE)
    load_backbone_and_head(
        model.backbone,
        model.aggregator,
        state,
        path,
        model_name="BoQ-DINOv2",
        backbone_prefixes=("backbone.dino.",),
        head_prefix="aggregator.",
        hint=f"expected {BOQ_DINOV2_FILE} from {BOQ_DINOV2_URL}",
    )
    return model.eval()
