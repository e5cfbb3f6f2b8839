"""Conv-AP (Ali-bey et al., "GSV-Cities", Neurocomputing 2022; amaralibey/gsv-cities):
the whole ResNet-50 trunk + a 1x1 convolution and 2 x 2 adaptive average pooling,
trained on GSV-Cities at 320 x 320.

Architecture (``VPRModel(backbone_arch="resnet50", layers_to_crop=[], agg_arch="ConvAP",
agg_config={in_channels: 2048, out_channels: 1024, s1: 2, s2: 2})``, plain torch here):

1. ``backbone.model``: torchvision ResNet-50 up to ``layer4``
   (:class:`vprflow.models.trunks.resnet.ResNet`) -> ``[B, 2048, H/32, W/32]``;
2. ``aggregator``: ``channel_pool`` (``Conv2d(2048, out_channels, 1)`` with bias), adaptive
   average pooling to ``s1 x s2`` = 2 x 2 (torch's bins: rows ``floor(i h / 2)`` to
   ``ceil((i + 1) h / 2)``), flattened channel-major (``channel * 4 + cell``) and
   L2-normalised: ``[B, 4 * out_channels]``.

Published dimensions (gsv-cities README): 8192 (``out_channels`` 2048), 4096 (1024, the
README's loading example, the default here), 2048 (512) and 512 (128). Any input size
works; the models were trained at 320 x 320 (the README: the 4096-d model with bicubic
resizing, the 8192-d one with bilinear), RGB normalised with ImageNet's mean / std.
Evaluated at 320 x 320 on the PIL image: the 4096-d model's MSLS-val and Nordland
numbers were printed by ``notebooks/evaluate_model.ipynb`` reading bicubic
(torchvision ``Resize(..., BICUBIC)``, commits 4ef23b2 to 252f6a0); from 5d866a0 on (the
cited commit 77ffffc too) that notebook reads bilinear, as the training code's
``valid_transform`` always did and vprflow's ``antialias`` does (docs/methods.md §11,
Conv-AP).

Checkpoint: e.g. ``resnet50_ConvAP_1024_2x2.ckpt`` (README's Google Drive folder), which
the README loads with ``model.load_state_dict``: a plain state dict of
``backbone.model.<torchvision name>`` (no ``fc``) and
``aggregator.channel_pool.{weight,bias}``; a Lightning checkpoint's ``"state_dict"``
with the same keys is accepted too. ``out_channels`` is read from the file.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from vprflow.models.checkpoints import CheckpointError
from vprflow.models.kinds import IMAGENET_MEAN, IMAGENET_STD, trained_model
from vprflow.models.trunks.resnet import TorchvisionBackbone
from vprflow.models.trunks.state_dicts import TRAINING_PREFIXES, load_matching, read_state

MEAN, STD = IMAGENET_MEAN, IMAGENET_STD
# The published file and input size (models/kinds.py's entry).
ENTRY = trained_model("convap")
INPUT_SIZE = ENTRY.height_width
# descriptor length -> channel_pool output channels (2 x 2 cells each)
CONVAP_DIMS = {8192: 2048, 4096: 1024, 2048: 512, 512: 128}
DEFAULT_DIM = ENTRY.published().loader_options["dim"]


class ConvAPAggregator(nn.Module):
    """``[B, in_channels, h, w]`` -> ``[B, out_channels * s1 * s2]`` (module docstring,
    step 2)."""

    def __init__(self, in_channels: int = 2048, out_channels: int = 1024, s1: int = 2, s2: int = 2):
        super().__init__()
        self.channel_pool = nn.Conv2d(in_channels, out_channels, kernel_size=1, bias=True)
        self.cells = (s1, s2)
        self.dim = out_channels * s1 * s2

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.adaptive_avg_pool2d(self.channel_pool(x), self.cells)
        return F.normalize(x.flatten(1), p=2, dim=1)


class ConvAP(nn.Module):
    """ResNet-50 ``layer4`` + :class:`ConvAPAggregator`.

    ``forward``: ImageNet-normalised ``[B, 3, H, W]`` -> L2-normalised ``[B, dim]``;
    ``feature_map``: the same input -> ``layer4`` ``[B, 2048, H/32, W/32]`` (what the
    aggregator reads) or another ResNet layer. State-dict keys are the checkpoint's.
    """

    def __init__(self, depth: int = 50, out_channels: int = 1024):
        super().__init__()
        self.backbone = TorchvisionBackbone(depth, "layer4")
        self.aggregator = ConvAPAggregator(self.backbone.dim, out_channels)
        self.dim = self.aggregator.dim
        self.input_size, self.mean, self.std = INPUT_SIZE, MEAN, STD

    def feature_map(self, images: torch.Tensor, layer: str = "layer4") -> torch.Tensor:
        return self.backbone.model.feature_map(images, layer)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.aggregator(self.backbone(images))


def load_convap(path: str, dim: int | None = None) -> ConvAP:
    """Conv-AP with the weights of ``path`` (module docstring's layout); its length is
    read from ``aggregator.channel_pool.weight``, and must equal ``dim`` when given
    (:data:`CONVAP_DIMS`). Raises :class:`~vprflow.models.checkpoints.CheckpointError`
    naming the file, the key at fault and where to get the published file."""
    if dim is not None and dim not in CONVAP_DIMS:
        raise ValueError(f"Conv-AP publishes no {dim}-d model; published: {sorted(CONVAP_DIMS)}")
    wanted = dim or DEFAULT_DIM
    # Only the 4096-d file's name is documented (the README's example).
    published = ENTRY.published()
    filename = published.file if wanted == DEFAULT_DIM else f"the {wanted}-d Conv-AP checkpoint"
    name, hint = f"Conv-AP {wanted}", f"expected {filename} from {published.url}"
    state = read_state(path, name, hint, containers=("state_dict",))
    weight = state.get("aggregator.channel_pool.weight")
    if not isinstance(weight, torch.Tensor) or weight.ndim != 4:
        raise CheckpointError(
            f"{name}: checkpoint {path!r} has no 4-d 'aggregator.channel_pool.weight' "
            f"(not the Conv-AP layout); {hint}"
        )
    model = ConvAP(out_channels=int(weight.shape[0]))
    if dim is not None and model.dim != dim:
        raise CheckpointError(
            f"{name}: checkpoint {path!r} key 'aggregator.channel_pool.weight' has shape "
            f"{tuple(weight.shape)}, giving {model.dim}-d descriptors, not {dim}; {hint}"
        )
    load_matching(model, state, path, name, hint, ignore=TRAINING_PREFIXES)
    return model.eval()
