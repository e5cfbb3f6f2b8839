"""VGG16's convolutional trunk in plain torch, in torchvision's exact state-dict layout.

:func:`vgg16_features` builds torchvision's ``vgg16().features``: 13 3x3 convolutions
(padding 1) with a ReLU after each and a 2x2 max-pool after each of the five stages, as
one ``nn.Sequential`` whose indices are torchvision's, so a torchvision state dict
(``features.0.weight`` ... ``features.28.bias``) loads key for key. Index 28 is
``conv5_3``; 29 its ReLU and 30 the last pool.

``end="conv5_3"`` stops after index 28, before the last ReLU and pool: this is the
trunk NetVLAD (Arandjelović et al.; Nanne/pytorch-NetVlad, QVPR/Patch-NetVLAD) puts its
pooling on, whose output can be negative. ``end="pool5"`` is the full ``features``.

Input: ImageNet-normalised ``[B, 3, H, W]``; output ``[B, 512, H/16, W/16]`` (conv5_3,
floor division at each of the four pools before it) or ``[B, 512, H/32, W/32]`` (pool5).
"""

from __future__ import annotations

import torch
from torch import nn

from vprflow.models.checkpoints import CheckpointError, read_checkpoint

# Channels of the 13 convolutions by stage; a 2x2 max-pool ends each stage
# (torchvision's configuration "D").
VGG16_STAGES = ((64, 64), (128, 128), (256, 256, 256), (512, 512, 512), (512, 512, 512))
# ``end`` -> how many modules of ``features`` are kept.
VGG16_ENDS = {"conv5_3": 29, "relu5_3": 30, "pool5": 31}
VGG16_DIM = 512
TORCHVISION_VGG16_URL = "https://download.pytorch.org/models/vgg16-397923af.pth"


def vgg16_features(end: str = "conv5_3") -> nn.Sequential:
    """torchvision's ``vgg16().features`` up to ``end`` (see :data:`VGG16_ENDS`)."""
    if end not in VGG16_ENDS:
        raise ValueError(f"unknown VGG16 end {end!r}; expected one of {sorted(VGG16_ENDS)}")
    layers: list[nn.Module] = []
    channels = 3
    for stage in VGG16_STAGES:
        for width in stage:
            layers += [nn.Conv2d(channels, width, kernel_size=3, padding=1), nn.ReLU()]
            channels = width
        layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
    return nn.Sequential(*layers[: VGG16_ENDS[end]])


class VGG16Trunk(nn.Module):
    """``features`` of torchvision's VGG16 up to ``end``; ``forward``: ``[B, 3, H, W]``
    ImageNet-normalised -> ``[B, 512, h, w]``. State-dict keys ``features.<i>.*``."""

    def __init__(self, end: str = "conv5_3"):
        super().__init__()
        self.end = end
        self.features = vgg16_features(end)
        self.dim = VGG16_DIM

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.features(images)


def load_vgg16_trunk(path: str, end: str = "conv5_3") -> VGG16Trunk:
    """A :class:`VGG16Trunk` with torchvision's ImageNet weights from ``path``
    (``vgg16-397923af.pth``; its ``classifier.*`` keys are not part of the trunk)."""
    trunk = VGG16Trunk(end)
    try:
        state = read_checkpoint(path)
    except CheckpointError as error:
        raise CheckpointError(
            f"VGG16 trunk: {error}; torchvision's ImageNet weights are at {TORCHVISION_VGG16_URL}"
        ) from error
    own = trunk.state_dict()
    wanted = {k: v for k, v in state.items() if k in own} if isinstance(state, dict) else {}
    missing = sorted(set(own) - set(wanted))
    if missing:
        raise CheckpointError(
            f"VGG16 trunk: checkpoint {path!r} lacks {missing[:4]} ({len(missing)} keys of "
            f"torchvision's features layout); torchvision's weights are at {TORCHVISION_VGG16_URL}"
        )
    for key, tensor in wanted.items():
        if tensor.shape != own[key].shape:
            raise CheckpointError(
                f"VGG16 trunk: checkpoint {path!r} key {key!r} has shape {tuple(tensor.shape)}, "
                f"expected {tuple(own[key].shape)}"
            )
    trunk.load_state_dict(wanted)
    return trunk.eval()
