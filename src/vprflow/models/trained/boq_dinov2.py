"""BoQ with a DINOv2 backbone (Ali-bey et al., CVPR 2024, updated arXiv 2405.07364 §4.5;
github.com/amaralibey/Bag-of-Queries): DINOv2-B/14 patch tokens + Bag-of-Queries,
12288-d at 322 x 322.

Architecture (``get_trained_boq(backbone_name="dinov2", output_dim=12288)``, plain
torch here):

1. backbone: DINOv2 ViT-B/14, all 12 blocks *without* the final LayerNorm (BoQ's
   ``DinoV2`` wrapper never calls it), position embeddings interpolated as the original
   DINOv2 code does; the patch tokens as a map ``[B, 768, H/14, W/14]`` (CLS dropped);
2. the BoQ head, :class:`vprflow.models.trained.boq.BoQAggregator` (``proj_channels =
   384``, 64 queries, 2 blocks, 6 heads, ``row_dim = 32``): ``proj_c`` (3x3
   convolution, padding 1, 768 -> 384), flatten to
   ``[B, n, 384]``, ``norm_input`` (LayerNorm); each block refines the tokens
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
``MultiheadAttention``, which the shared head uses as they are.
"""

from __future__ import annotations

import torch
from torch import nn

from vprflow.models.kinds import IMAGENET_MEAN, IMAGENET_STD, trained_model
from vprflow.models.trained.boq import BoQAggregator
from vprflow.models.trunks.dinov2 import DinoV2Tokens, load_backbone_and_head
from vprflow.models.trunks.state_dicts import read_state_dict

MEAN, STD = IMAGENET_MEAN, IMAGENET_STD
# The published file and input size (models/kinds.py's entry).
ENTRY = trained_model("boq_dinov2")
INPUT_SIZE = ENTRY.height_width
PROJ_CHANNELS = 384  # 6 heads; the ResNet-50 variant projects to 512


class BoQDinoV2(nn.Module):
    """``forward``: ImageNet-normalised ``[B, 3, H, W]`` (multiples of 14; 322 x 322
    published) -> ``[B, 12288]``; ``feature_map``: the same input -> DINOv2's last-block
    patch tokens (no final norm) ``[B, 768, H/14, W/14]``."""

    def __init__(self, config=None, **aggregator):
        super().__init__()
        self.backbone = DinoV2Tokens(config, final_norm=False)
        sizes = {"proj_channels": PROJ_CHANNELS, **aggregator}
        self.aggregator = BoQAggregator(self.backbone.dim, **sizes)
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
    fault and where to get the published file."""
    model = BoQDinoV2(config, **aggregator)
    published = ENTRY.published()
    state = read_state_dict(path, "BoQ-DINOv2", published.url, published.file)
    load_backbone_and_head(
        model.backbone,
        model.aggregator,
        state,
        path,
        model_name="BoQ-DINOv2",
        backbone_prefixes=("backbone.dino.",),
        head_prefix="aggregator.",
        hint=published.hint,
    )
    return model.eval()
