"""BoQ with a ResNet-50 backbone (Ali-bey et al., "BoQ: A Place is Worth a Bag of
Learnable Queries", CVPR 2024; amaralibey/Bag-of-Queries): ResNet-50 cut after
``layer3`` + Bag-of-Queries, 16384-d at 384 x 384, trained on GSV-Cities.

Architecture (``get_trained_boq(backbone_name="resnet50", output_dim=16384)``, plain
torch here; the DINOv2 variant is :mod:`vprflow.models.trained.boq_dinov2`):

1. ``backbone.net``: torchvision ResNet-50 children ``conv1`` ... ``layer3`` as an
   ``nn.Sequential`` (``net.0`` ``conv1``, ``net.1`` ``bn1``, ``net.4`` ... ``net.6``
   ``layer1`` ... ``layer3``) -> ``[B, 1024, H/16, W/16]``;
2. ``aggregator`` (``proj_channels = 512``, 64 queries, 2 blocks of 8 heads,
   ``row_dim = 32``): ``proj_c`` (3x3 convolution, padding 1, 1024 -> 512), flattened to
   tokens ``[B, n, 512]``, ``norm_input`` (LayerNorm). Each block: the tokens pass a
   post-norm ``nn.TransformerEncoderLayer`` (ReLU MLP of 4 x 512, no dropout); the learned
   ``queries`` ``[1, 64, 512]`` get ``norm_q(q + self_attn(q, q, q))`` and cross-attend to
   the refined tokens (``cross_attn``), then ``norm_out``: ``[B, 64, 512]``. The blocks'
   outputs are concatenated over queries (``[B, 128, 512]``); ``fc``
   (``Linear(128, 32)``) maps queries to rows per channel (``[B, 512, 32]``), flattened
   as ``channel * 32 + row`` and L2-normalised: ``[B, 16384]``.

Input: RGB in [0, 1] resized to 384 x 384 (bicubic, antialiased; BoQ's README) and
normalised with ImageNet's mean / std. Any size works (the aggregator attends over
however many tokens there are).

Checkpoint: ``resnet50_16384.pth``
(github.com/amaralibey/Bag-of-Queries/releases/download/v1.0), a plain state dict read
with ``torch.load(weights_only=True)``: ``backbone.net.<i>.*`` in torchvision's block
names and ``aggregator.{proj_c, norm_input, boqs.<i>.{encoder.{self_attn.in_proj_*,
self_attn.out_proj.*, linear1, linear2, norm1, norm2}, queries, self_attn.*, norm_q,
cross_attn.*, norm_out}, fc}.*``, torch's ``TransformerEncoderLayer`` /
``MultiheadAttention`` names, which this module uses as they are.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from vprflow.models.kinds import IMAGENET_MEAN, IMAGENET_STD, trained_model
from vprflow.models.trunks.resnet import (
    ResNet,
    resnet_channels,
    stage_maps,
)
from vprflow.models.trunks.state_dicts import load_matching, read_state

MEAN, STD = IMAGENET_MEAN, IMAGENET_STD
# The published file and input size (models/kinds.py's entry).
ENTRY = trained_model("boq_resnet50")
INPUT_SIZE = ENTRY.height_width


class QueryBlock(nn.Module):
    """One Bag-of-Queries block: tokens ``[B, n, E]`` -> ``(refined tokens [B, n, E],
    query outputs [B, Q, E])`` (module docstring, step 2)."""

    def __init__(self, dim: int, num_queries: int, heads: int):
        super().__init__()
        self.encoder = nn.TransformerEncoderLayer(
            d_model=dim, nhead=heads, dim_feedforward=4 * dim, dropout=0.0, batch_first=True
        )
        self.queries = nn.Parameter(torch.zeros(1, num_queries, dim))
        # Acts on the learned queries alone (the same for every image); BoQ computes
        # it on every call, and so does this module, to stay equal to it.
        self.self_attn = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.norm_q = nn.LayerNorm(dim)
        self.cross_attn = nn.MultiheadAttention(dim, heads, batch_first=True)
        self.norm_out = nn.LayerNorm(dim)

    def forward(self, tokens: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        tokens = self.encoder(tokens)
        queries = self.queries.expand(tokens.shape[0], -1, -1)
        queries = self.norm_q(
            queries + self.self_attn(queries, queries, queries, need_weights=False)[0]
        )
        out = self.cross_attn(queries, tokens, tokens, need_weights=False)[0]
        return tokens, self.norm_out(out)


class BoQAggregator(nn.Module):
    """``[B, in_channels, h, w]`` -> ``[B, proj_channels * row_dim]`` (module docstring,
    step 2); ``proj_channels / 64`` heads. Both BoQ variants' head: ResNet-50's with
    these defaults, DINOv2's with ``in_channels=768, proj_channels=384``."""

    def __init__(
        self,
        in_channels: int = 1024,
        proj_channels: int = 512,
        num_queries: int = 64,
        num_layers: int = 2,
        row_dim: int = 32,
    ):
        super().__init__()
        self.proj_c = nn.Conv2d(in_channels, proj_channels, kernel_size=3, padding=1)
        self.norm_input = nn.LayerNorm(proj_channels)
        self.boqs = nn.ModuleList(
            QueryBlock(proj_channels, num_queries, proj_channels // 64) for _ in range(num_layers)
        )
        self.fc = nn.Linear(num_layers * num_queries, row_dim)
        self.dim = proj_channels * row_dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        tokens = self.norm_input(self.proj_c(x).flatten(2).transpose(1, 2))
        outputs = []
        for block in self.boqs:
            tokens, out = block(tokens)
            outputs.append(out)
        rows = self.fc(torch.cat(outputs, dim=1).transpose(1, 2))  # [B, E, row_dim]
        return F.normalize(rows.flatten(1), p=2, dim=-1)


class _Net(nn.Module):
    """BoQ's ``ResNet`` wrapper: the trunk's children under ``net.<i>``."""

    def __init__(self, depth: int):
        super().__init__()
        self.net = nn.Sequential(*ResNet(depth, "layer3").stages())

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.net(images)


class BoQResNet(nn.Module):
    """ResNet-50 ``layer3`` + :class:`BoQAggregator`.

    ``forward``: ImageNet-normalised ``[B, 3, H, W]`` -> L2-normalised ``[B, 16384]``;
    ``feature_map``: the same input -> ``layer3`` ``[B, 1024, H/16, W/16]`` (what the
    aggregator reads) or an earlier layer. State-dict keys are the checkpoint's.
    """

    def __init__(self, depth: int = 50, **aggregator):
        super().__init__()
        self.backbone = _Net(depth)
        channels = resnet_channels(depth, "layer3")
        self.aggregator = BoQAggregator(channels, **aggregator)
        self.dim = self.aggregator.dim
        self.input_size, self.mean, self.std = INPUT_SIZE, MEAN, STD

    def feature_map(self, images: torch.Tensor, layer: str = "layer3") -> torch.Tensor:
        return stage_maps(list(self.backbone.net), images, [layer])[layer]

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.aggregator(self.backbone(images))


def load_boq_resnet50(path: str, **aggregator) -> BoQResNet:
    """BoQ-ResNet-50 with the weights of ``path`` (``resnet50_16384.pth`` layout, module
    docstring); ``aggregator`` replaces the published head sizes (tests). Raises
    :class:`~vprflow.models.checkpoints.CheckpointError` naming the file, the key at
    fault and where to get the published file."""
    name, hint = "BoQ-ResNet50", ENTRY.published().hint
    model = BoQResNet(**aggregator)
    load_matching(model, read_state(path, name, hint), path, name, hint)
    return model.eval()
