"""MegaLoc (Berton & Masone, CVPRW 2025; github.com/gmberton/MegaLoc): DINOv2-B/14 +
SALAD-style optimal-transport aggregation + a linear projection, 8448-d.

Architecture (``megaloc_model.MegaLoc``, plain torch here):

1. an input whose sides are not multiples of 14 is resized to the nearest multiples
   (``round(side / 14) * 14``; bilinear with antialiasing, torchvision's tensor
   ``resize``), as MegaLoc's ``forward`` does;
2. backbone: DINOv2 ViT-B/14, 12 blocks and the final LayerNorm, position embeddings
   interpolated as the original DINOv2 code does (the same
   :class:`vprflow.models.trunks.dinov2.DinoV2Tokens` as SALAD): CLS token
   ``[B, 768]`` and patch map ``[B, 768, H/14, W/14]``;
3. :class:`~vprflow.models.trained.salad.SaladAggregator` with ``m = 64`` clusters of
   ``l = 256`` dims (SALAD: 128), a 256-d scene token and 512-wide MLPs:
   ``256 + 64 * 256 = 16640``-d, L2-normalised;
4. ``Linear(16640, 8448)`` then L2 normalisation: ``[B, 8448]``.

Input: RGB in [0, 1] normalised with ImageNet's mean / std at the images' own size
(:data:`INPUT_SIZE` is ``None``): MegaLoc's evaluation code, gmberton/VPR-methods-evaluation,
resizes nothing by default (``--image_size None``) and MegaLoc's ``forward`` rounds each
side to a multiple of 14 itself (step 1).

Checkpoint: ``model.safetensors`` of huggingface.co/gberton/MegaLoc (keys
``backbone.<torch-hub DINOv2 name>`` without ``mask_token``, ``aggregator.agg.*`` in
SALAD's layout, ``aggregator.linear.{weight,bias}``), read with safetensors; the older
release ``megaloc.torch`` (github.com/gmberton/MegaLoc/releases/download/v1.0), a
``torch.load(weights_only=True)`` state dict whose backbone sits under
``backbone.model.``, loads too.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from vprflow.models.kinds import IMAGENET_MEAN, IMAGENET_STD, trained_model
from vprflow.models.trained.salad import SaladAggregator
from vprflow.models.trunks.dinov2 import DinoV2Tokens, load_backbone_and_head
from vprflow.models.trunks.state_dicts import read_state_dict

MEAN, STD = IMAGENET_MEAN, IMAGENET_STD
# The published file and input size (models/kinds.py's entry): None, the images' own
# size, rounded to multiples of 14 by the model (step 1).
ENTRY = trained_model("megaloc")
INPUT_SIZE = ENTRY.height_width
MEGALOC_DIM = 8448


class MegaLocHead(nn.Module):
    """``agg`` (SALAD aggregation) then ``linear``: ``(x, t)`` -> ``[B, feat_dim]``
    (not normalised; MegaLoc normalises after it). Keys as MegaLoc's ``Aggregator``."""

    def __init__(
        self,
        num_channels: int = 768,
        feat_dim: int = MEGALOC_DIM,
        num_clusters: int = 64,
        cluster_dim: int = 256,
        token_dim: int = 256,
        mlp_dim: int = 512,
    ):
        super().__init__()
        self.agg = SaladAggregator(num_channels, num_clusters, cluster_dim, token_dim, mlp_dim)
        self.linear = nn.Linear(self.agg.dim, feat_dim)

    def forward(self, x: torch.Tensor, token: torch.Tensor) -> torch.Tensor:
        return self.linear(self.agg(x, token))


class MegaLoc(nn.Module):
    """``forward``: ImageNet-normalised ``[B, 3, H, W]`` -> L2-normalised
    ``[B, feat_dim]`` (8448); ``feature_map``: the (resized) input -> normed DINOv2
    patch tokens ``[B, 768, H/14, W/14]``."""

    def __init__(
        self,
        config=None,
        *,
        feat_dim: int = MEGALOC_DIM,
        num_clusters: int = 64,
        cluster_dim: int = 256,
        token_dim: int = 256,
        mlp_dim: int = 512,
    ):
        super().__init__()
        self.backbone = DinoV2Tokens(config, final_norm=True)
        self.aggregator = MegaLocHead(
            self.backbone.dim, feat_dim, num_clusters, cluster_dim, token_dim, mlp_dim
        )
        self.dim = feat_dim
        self.input_size, self.mean, self.std = INPUT_SIZE, MEAN, STD

    def _resize(self, images: torch.Tensor) -> torch.Tensor:
        patch = self.backbone.patch_size
        height, width = images.shape[-2:]
        if height % patch == 0 and width % patch == 0:
            return images
        size = [round(height / patch) * patch, round(width / patch) * patch]
        return F.interpolate(
            images, size=size, mode="bilinear", align_corners=False, antialias=True
        )

    def feature_map(self, images: torch.Tensor) -> torch.Tensor:
        return self.backbone(self._resize(images))[0]

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return F.normalize(self.aggregator(*self.backbone(self._resize(images))), p=2, dim=1)


def load_megaloc(path: str, config=None, **sizes) -> MegaLoc:
    """MegaLoc with the weights of ``path`` (``model.safetensors`` or ``megaloc.torch``,
    module docstring). ``config`` / ``sizes`` replace the published sizes (tests).
    Raises :class:`~vprflow.models.checkpoints.CheckpointError` naming the file, the
    key at fault and where to get the published file."""
    model = MegaLoc(config, **sizes)
    published = ENTRY.published()
    state = read_state_dict(path, "MegaLoc", published.url, published.file)
    load_backbone_and_head(
        model.backbone,
        model.aggregator,
        state,
        path,
        model_name="MegaLoc",
        backbone_prefixes=("backbone.", "backbone.model."),
        head_prefix="aggregator.",
        hint=published.hint,
    )
    return model.eval()
