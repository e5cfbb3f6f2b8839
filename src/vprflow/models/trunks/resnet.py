"""ResNet-18/34/50/101/152 in plain torch, in torchvision's exact state-dict layout.

:class:`ResNet` builds torchvision's ``resnet<depth>()`` (He et al. 2016, "v1.5": a
bottleneck's stride sits on its 3x3 convolution): ``conv1`` (7x7, stride 2, no bias),
``bn1``, ``relu``, ``maxpool`` (3x3, stride 2, padding 1), ``layer1`` ... ``layer4``
(blocks ``<i>.{conv1, bn1, conv2, bn2[, conv3, bn3]}`` and, on the first block of a
stage that changes shape, ``<i>.downsample.{0 (1x1 conv), 1 (BatchNorm)}``) and, with
``classifier=True``, ``avgpool`` + ``fc``. BatchNorms keep torchvision's eps 1e-5 and
buffers (``running_mean``, ``running_var``, ``num_batches_tracked``), so a torchvision
checkpoint (``resnet50-0676ba61.pth`` ...) loads key for key.

The VPR models keep the trunk up to ``end``: MixVPR and BoQ cut it after ``layer3``,
CosPlace / EigenPlaces / ConvAP after ``layer4``. SNSM (Revisit-Anything's
All-Backbones-VLAD_bl.py) reads the maps of ``layer1`` ... ``layer4``:
:meth:`ResNet.feature_maps` returns any of them from one pass.

Input: ImageNet-normalised ``[B, 3, H, W]``. Map of ``layer<k>``:
``[B, C_k, ceil(H / 2^(k+1)), ceil(W / 2^(k+1))]`` (for sizes divisible by 32:
``H / 4, H / 8, H / 16, H / 32``); ``C_k = 64 * 2^(k-1)`` for ResNet-18/34 and four
times that (256, 512, 1024, 2048) for the bottleneck ResNets.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import torch
from torch import nn

from vprflow.models.kinds import TORCHVISION_RESNET_URLS
from vprflow.models.trunks.state_dicts import load_matching, read_state

# depth -> (block kind, blocks per stage), torchvision's configurations.
RESNET_DEPTHS = {
    18: ("basic", (2, 2, 2, 2)),
    34: ("basic", (3, 4, 6, 3)),
    50: ("bottleneck", (3, 4, 6, 3)),
    101: ("bottleneck", (3, 4, 23, 3)),
    152: ("bottleneck", (3, 8, 36, 3)),
}
LAYERS = ("layer1", "layer2", "layer3", "layer4")
# torchvision's child order; models that wrap the trunk in an ``nn.Sequential``
# (CosPlace's ``backbone.<i>``, BoQ's ``backbone.net.<i>``) index it this way.
STAGES = ("conv1", "bn1", "relu", "maxpool", *LAYERS)
LAYER_STRIDES = {"layer1": 4, "layer2": 8, "layer3": 16, "layer4": 32}


def _check_depth(depth: int) -> None:
    if depth not in RESNET_DEPTHS:
        raise ValueError(f"unknown ResNet depth {depth!r}; expected one of {sorted(RESNET_DEPTHS)}")


def _check_layer(layer: str) -> None:
    if layer not in LAYERS:
        raise ValueError(f"unknown ResNet layer {layer!r}; expected one of {LAYERS}")


def resnet_channels(depth: int, layer: str = "layer4") -> int:
    """Channels of ``layer``'s map in ResNet-``depth`` (512 / 2048 for ``layer4``)."""
    _check_depth(depth)
    _check_layer(layer)
    expansion = 1 if RESNET_DEPTHS[depth][0] == "basic" else 4
    return 64 * 2 ** LAYERS.index(layer) * expansion


def _downsample(inplanes: int, planes: int, stride: int) -> nn.Sequential | None:
    if stride == 1 and inplanes == planes:
        return None
    return nn.Sequential(
        nn.Conv2d(inplanes, planes, kernel_size=1, stride=stride, bias=False),
        nn.BatchNorm2d(planes),
    )


class BasicBlock(nn.Module):
    """Two 3x3 convolutions (the first strided) with a residual; ResNet-18/34.
    ``[B, inplanes, h, w]`` -> ``[B, planes, h / stride, w / stride]``."""

    expansion = 1

    def __init__(self, inplanes: int, planes: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(inplanes, planes, 3, stride=stride, padding=1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = _downsample(inplanes, planes, stride)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        shortcut = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        return self.relu(self.bn2(self.conv2(out)) + shortcut)


class Bottleneck(nn.Module):
    """1x1 -> 3x3 (strided, torchvision's "v1.5") -> 1x1 (x4 channels) with a residual;
    ResNet-50/101/152. ``[B, inplanes, h, w]`` -> ``[B, 4 planes, h / stride, w / stride]``."""

    expansion = 4

    def __init__(self, inplanes: int, planes: int, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(inplanes, planes, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = nn.Conv2d(planes, planes, 3, stride=stride, padding=1, bias=False)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = nn.Conv2d(planes, planes * 4, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(planes * 4)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = _downsample(inplanes, planes * 4, stride)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        shortcut = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        return self.relu(self.bn3(self.conv3(out)) + shortcut)


def stage_maps(
    stages: Sequence[nn.Module], images: torch.Tensor, layers: Iterable[str]
) -> dict[str, torch.Tensor]:
    """``{layer: map}`` for each of ``layers`` from one pass through ``stages`` (the
    trunk's modules in :data:`STAGES` order, possibly cut short); stops at the deepest
    requested layer. ``images``: ImageNet-normalised ``[B, 3, H, W]``."""
    wanted = list(dict.fromkeys(layers))
    for layer in wanted:
        _check_layer(layer)
        if STAGES.index(layer) >= len(stages):
            raise ValueError(
                f"ResNet layer {layer!r} is not part of this trunk, which ends at "
                f"{STAGES[len(stages) - 1]!r}"
            )
    last = max(STAGES.index(layer) for layer in wanted)
    maps: dict[str, torch.Tensor] = {}
    x = images
    for name, module in zip(STAGES[: last + 1], stages, strict=False):
        x = module(x)
        if name in wanted:
            maps[name] = x
    return maps


class ResNet(nn.Module):
    """torchvision's ``resnet<depth>`` up to ``end`` (module docstring); with
    ``classifier=True`` (``end="layer4"`` only) also ``avgpool`` and ``fc``.

    ``forward``: ImageNet-normalised ``[B, 3, H, W]`` -> the ``end`` map ``[B, C, h, w]``
    (the classifier's logits ``[B, num_classes]`` when it has one).
    """

    def __init__(
        self,
        depth: int = 50,
        end: str = "layer4",
        *,
        classifier: bool = False,
        num_classes: int = 1000,
    ):
        super().__init__()
        _check_depth(depth)
        _check_layer(end)
        if classifier and end != "layer4":
            raise ValueError(
                f"a ResNet classifier needs the whole trunk (end='layer4'), not {end!r}"
            )
        kind, blocks = RESNET_DEPTHS[depth]
        block = BasicBlock if kind == "basic" else Bottleneck
        self.depth, self.end, self.classifier = depth, end, classifier
        self.conv1 = nn.Conv2d(3, 64, kernel_size=7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(64)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        inplanes = 64
        for index, count in enumerate(blocks[: LAYERS.index(end) + 1]):
            planes = 64 * 2**index
            stride = 1 if index == 0 else 2
            stage = []
            for position in range(count):
                stage.append(block(inplanes, planes, stride if position == 0 else 1))
                inplanes = planes * block.expansion
            setattr(self, LAYERS[index], nn.Sequential(*stage))
        self.dim = inplanes
        if classifier:
            self.avgpool = nn.AdaptiveAvgPool2d(1)
            self.fc = nn.Linear(inplanes, num_classes)

    def stages(self) -> list[nn.Module]:
        """The trunk's modules in :data:`STAGES` order, up to ``end``."""
        return [getattr(self, name) for name in STAGES[: STAGES.index(self.end) + 1]]

    def feature_maps(self, images: torch.Tensor, layers: Iterable[str]) -> dict[str, torch.Tensor]:
        """``{layer: [B, C_layer, h, w]}`` for each requested layer, from one pass."""
        return stage_maps(self.stages(), images, layers)

    def feature_map(self, images: torch.Tensor, layer: str | None = None) -> torch.Tensor:
        """The map of ``layer`` (default ``end``): ``[B, C_layer, h, w]``."""
        layer = layer or self.end
        return self.feature_maps(images, [layer])[layer]

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = self.feature_map(images)
        if not self.classifier:
            return x
        return self.fc(torch.flatten(self.avgpool(x), 1))


class TorchvisionBackbone(nn.Module):
    """amaralibey's ``ResNet`` backbone wrapper (MixVPR, Conv-AP): the trunk under
    ``model``, so its keys read ``backbone.model.<torchvision name>``. ``[B, 3, H, W]``
    -> ``end`` map."""

    def __init__(self, depth: int = 50, end: str = "layer3"):
        super().__init__()
        self.model = ResNet(depth, end)
        self.dim = self.model.dim

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.model(images)


def load_resnet(
    path: str, depth: int = 50, end: str = "layer4", *, classifier: bool = False
) -> ResNet:
    """A :class:`ResNet` with the weights of a torchvision checkpoint ``path``
    (``resnet<depth>-*.pth``, a plain state dict). Keys beyond ``end`` (later layers,
    ``fc``) are ignored unless ``classifier``; any other difference from torchvision's
    ``resnet<depth>`` layout is a :class:`CheckpointError` naming the file and key."""
    _check_depth(depth)
    _check_layer(end)
    trunk = ResNet(depth, end, classifier=classifier)
    name = f"ResNet-{depth} trunk"
    hint = f"torchvision's ImageNet weights are at {TORCHVISION_RESNET_URLS[depth]}"
    state = read_state(path, name, hint)
    dropped = [f"{layer}." for layer in LAYERS[LAYERS.index(end) + 1 :]]
    if not classifier:
        dropped.append("fc.")
    load_matching(trunk, state, path, name, hint, ignore=dropped)
    return trunk.eval()
