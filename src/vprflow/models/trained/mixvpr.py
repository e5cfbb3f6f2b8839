"""MixVPR (Ali-bey et al., WACV 2023; amaralibey/MixVPR): ResNet-50 cut after ``layer3``
+ feature mixing, 4096-d at 320 x 320, trained on GSV-Cities.

Architecture (``VPRModel(backbone_arch="resnet50", layers_to_crop=[4], agg_arch="MixVPR",
agg_config={in_channels: 1024, in_h: 20, in_w: 20, out_channels: 1024, mix_depth: 4,
mlp_ratio: 1, out_rows: 4})``, plain torch here):

1. ``backbone.model``: torchvision ResNet-50 up to ``layer3``
   (:class:`vprflow.models.trunks.resnet.ResNet`) -> ``[B, 1024, H/16, W/16]``;
2. ``aggregator``: the map flattened to ``[B, 1024, n]`` (``n = h * w`` = 400 at
   320 x 320); ``mix_depth`` feature mixers, each ``x + Linear(ReLU(Linear(LayerNorm(x))))``
   over the ``n`` positions of every channel (``mix.<i>.mix.{0, 1, 3}``, hidden width
   ``n * mlp_ratio``); ``channel_proj`` (``Linear(1024, out_channels)``) over channels;
   ``row_proj`` (``Linear(n, out_rows)``) over positions; flattened channel-major
   (``channel * out_rows + row``) and L2-normalised: ``[B, out_channels * out_rows]``.

The mixers fix ``n``, so the input size is fixed: 320 x 320 for the published models,
RGB normalised with ImageNet's mean / std. The repository's only evaluation code,
``main.py``'s validation (Pittsburgh 30k, MSLS-val) through
``dataloaders/GSVCitiesDataloader.py``'s ``valid_transform`` (line 83), resizes the PIL
image with torchvision's ``Resize(..., BILINEAR)`` (PIL's antialiased bilinear), which
vprflow's ``antialias`` reproduces; ``demo.py``, a contributor's added five months
after the README's numbers, resizes bicubically (docs/methods.md §11, MixVPR).

Checkpoint: ``resnet50_MixVPR_4096_channels(1024)_rows(4).ckpt`` (README's Google Drive
link; the README's 512-d and 128-d releases load too, as the loader reads the head's
sizes from the file). The README loads it with ``model.load_state_dict``:
a plain state dict of ``backbone.model.<torchvision name>`` (no ``layer4`` / ``fc``)
and ``aggregator.{mix.<i>.mix.{0,1,3}, channel_proj, row_proj}.*``; a Lightning
checkpoint's ``"state_dict"`` holding the same keys is accepted too.
"""

from __future__ import annotations

import math
import re

import torch
from torch import nn
from torch.nn import functional as F

from vprflow.models.checkpoints import CheckpointError
from vprflow.models.kinds import IMAGENET_MEAN, IMAGENET_STD, trained_model
from vprflow.models.trunks.resnet import (
    LAYER_STRIDES,
    TorchvisionBackbone,
)
from vprflow.models.trunks.state_dicts import TRAINING_PREFIXES, load_matching, read_state

MEAN, STD = IMAGENET_MEAN, IMAGENET_STD
# The published file (models/kinds.py's entry); the loader reads the sizes from the file.
PUBLISHED = trained_model("mixvpr").published()


class FeatureMixer(nn.Module):
    """``x + Linear(ReLU(Linear(LayerNorm(x))))`` over the last dimension:
    ``[B, C, n]`` -> ``[B, C, n]``; parameters ``mix.{0, 1, 3}`` as in MixVPR."""

    def __init__(self, positions: int, mlp_ratio: float = 1.0):
        super().__init__()
        hidden = int(positions * mlp_ratio)
        self.mix = nn.Sequential(
            nn.LayerNorm(positions),
            nn.Linear(positions, hidden),
            nn.ReLU(),
            nn.Linear(hidden, positions),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.mix(x)


class MixVPRAggregator(nn.Module):
    """``[B, in_channels, h, w]`` with ``h * w == positions`` -> ``[B, out_channels *
    out_rows]`` (module docstring, step 2)."""

    def __init__(
        self,
        in_channels: int = 1024,
        positions: int = 400,
        out_channels: int = 1024,
        mix_depth: int = 4,
        mlp_ratio: float = 1.0,
        out_rows: int = 4,
    ):
        super().__init__()
        self.positions = positions
        self.mix = nn.Sequential(*(FeatureMixer(positions, mlp_ratio) for _ in range(mix_depth)))
        self.channel_proj = nn.Linear(in_channels, out_channels)
        self.row_proj = nn.Linear(positions, out_rows)
        self.dim = out_channels * out_rows

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x.flatten(2)
        if x.shape[2] != self.positions:
            raise ValueError(
                f"MixVPR's mixers take maps of {self.positions} positions; got "
                f"{x.shape[2]} (input of another size than it was trained for)"
            )
        x = self.mix(x)
        x = self.channel_proj(x.transpose(1, 2))  # [B, n, out_channels]
        x = self.row_proj(x.transpose(1, 2))  # [B, out_channels, out_rows]
        return F.normalize(x.flatten(1), p=2, dim=-1)


class MixVPR(nn.Module):
    """ResNet-50 ``layer3`` + :class:`MixVPRAggregator`.

    ``forward``: ImageNet-normalised ``[B, 3, H, W]`` (``H * W / 256`` must equal the
    mixers' ``positions``: 320 x 320 published) -> L2-normalised ``[B, dim]``;
    ``feature_map``: the same input -> ``layer3`` ``[B, 1024, H/16, W/16]`` (what the
    aggregator reads) or another layer up to it. State-dict keys are the checkpoint's.
    """

    def __init__(self, depth: int = 50, **aggregator):
        super().__init__()
        self.backbone = TorchvisionBackbone(depth, "layer3")
        self.aggregator = MixVPRAggregator(self.backbone.dim, **aggregator)
        self.dim = self.aggregator.dim
        side = int(math.isqrt(self.aggregator.positions)) * LAYER_STRIDES["layer3"]
        self.input_size, self.mean, self.std = (side, side), MEAN, STD

    def feature_map(self, images: torch.Tensor, layer: str = "layer3") -> torch.Tensor:
        return self.backbone.model.feature_map(images, layer)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.aggregator(self.backbone(images))


def load_mixvpr(path: str) -> MixVPR:
    """MixVPR with the weights of ``path`` (module docstring's layout). The mixer depth,
    ``positions``, ``out_channels`` and ``out_rows`` are read from the file's shapes, so
    the 4096-, 512- and 128-d releases all load. Raises
    :class:`~vprflow.models.checkpoints.CheckpointError` naming the file, the key at
    fault and where to get the published file."""
    name, hint = "MixVPR", PUBLISHED.hint
    state = read_state(path, name, hint, containers=("state_dict",))
    shapes = {}
    for key in ("aggregator.row_proj.weight", "aggregator.channel_proj.weight"):
        tensor = state.get(key)
        if not isinstance(tensor, torch.Tensor) or tensor.ndim != 2:
            raise CheckpointError(
                f"{name}: checkpoint {path!r} has no 2-d {key!r} (not the MixVPR layout); {hint}"
            )
        shapes[key] = tuple(tensor.shape)
    out_rows, positions = shapes["aggregator.row_proj.weight"]
    out_channels = shapes["aggregator.channel_proj.weight"][0]
    mixers = {m.group(1) for k in state if (m := re.match(r"aggregator\.mix\.(\d+)\.", str(k)))}
    hidden = state.get("aggregator.mix.0.mix.1.weight")
    mlp_ratio = hidden.shape[0] / positions if isinstance(hidden, torch.Tensor) else 1.0
    model = MixVPR(
        positions=positions,
        out_channels=out_channels,
        mix_depth=len(mixers),
        mlp_ratio=mlp_ratio,
        out_rows=out_rows,
    )
    load_matching(model, state, path, name, hint, ignore=TRAINING_PREFIXES)
    return model.eval()
