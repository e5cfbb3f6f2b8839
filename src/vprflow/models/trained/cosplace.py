"""CosPlace (Berton et al., CVPR 2022; gmberton/CosPlace) and EigenPlaces (Berton et al.,
ICCV 2023; gmberton/EigenPlaces): a ResNet trunk + GeM + fully connected + L2, trained
on SF-XL. Both repositories build the same ``GeoLocalizationNet``; only the weights and
the published dimensions differ.

Architecture (plain torch here):

1. ``backbone``: torchvision ``resnet<depth>`` children up to ``layer4`` (avgpool and fc
   removed) as an ``nn.Sequential``, so ``backbone.0`` is ``conv1``, ``backbone.1``
   ``bn1``, ``backbone.4`` ... ``backbone.7`` ``layer1`` ... ``layer4``
   (:data:`vprflow.models.trunks.resnet.STAGES`) -> ``x`` ``[B, C, H/32, W/32]``
   (``C`` = 2048 for ResNet-50/101/152, 512 for ResNet-18);
2. ``aggregation``: ``x`` L2-normalised over channels at every position; GeM
   ``(mean_p max(x, 1e-6)^p)^(1/p)`` with the learned ``p`` (``aggregation.1.p``,
   ``[1]``) -> ``[B, C]``; ``aggregation.3`` (``Linear(C, dim)``); L2 -> ``[B, dim]``.

Input: RGB in [0, 1] normalised with ImageNet's mean / std, at the images' own size
(both repositories test without resizing unless ``--resize_test_imgs``, which resizes
the shorter side to 512). ``input_size`` is therefore ``None``.

Checkpoints: ``<Backbone>_<dim>_cosplace.pth`` / ``<Backbone>_<dim>_eigenplaces.pth``
from the repositories' v1.0 releases (what their ``torch.hub`` entry points download),
plain state dicts read with ``torch.load(weights_only=True)``: ``backbone.<i>.*`` in
torchvision's block names, ``aggregation.1.p``, ``aggregation.3.{weight,bias}``.
Published (:data:`COSPLACE_DIMS`, :data:`EIGENPLACES_DIMS`); the default is ResNet-50
at 2048, the variant Revisit-Anything's and both papers' main tables use. CosPlace's
VGG16 variants are not built here.
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
INPUT_SIZE = trained_model("cosplace").height_width  # None: the images' own size
BACKBONES = {"ResNet18": 18, "ResNet50": 50, "ResNet101": 101, "ResNet152": 152}


def _published(kind: str) -> dict[str, tuple[int, ...]]:
    """ResNet backbone -> the published descriptor lengths: the variants of ``kind``'s
    entry in models/kinds.py, which names each file and where it is."""
    options = [v.loader_options for v in trained_model(kind).variants.values()]
    return {
        backbone: tuple(sorted(o["dim"] for o in options if o["backbone"] == backbone))
        for backbone in BACKBONES
        if any(o["backbone"] == backbone for o in options)
    }


COSPLACE_DIMS = _published("cosplace")
EIGENPLACES_DIMS = _published("eigenplaces")
_DEFAULT = trained_model("cosplace").published().loader_options
DEFAULT_BACKBONE, DEFAULT_DIM = _DEFAULT["backbone"], _DEFAULT["dim"]


class ChannelL2(nn.Module):
    """L2 normalisation over dimension 1 (channels of a map, or a descriptor)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.normalize(x, p=2.0, dim=1)


class GeM(nn.Module):
    """Generalised mean pooling (Radenović et al.) over all positions with a learned
    exponent ``p`` (``[1]``, initialised to 3): ``[B, C, h, w]`` -> ``[B, C, 1, 1]``,
    ``(mean_{h,w} max(x, eps)^p)^(1/p)``."""

    def __init__(self, p: float = 3.0, eps: float = 1e-6):
        super().__init__()
        self.p = nn.Parameter(torch.full((1,), float(p)))
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        pooled = x.clamp(min=self.eps).pow(self.p).mean(dim=(-2, -1), keepdim=True)
        return pooled.pow(1.0 / self.p)


class GeoLocalizationNet(nn.Module):
    """CosPlace / EigenPlaces (module docstring) for a ResNet ``backbone`` name
    (:data:`BACKBONES`) and descriptor length ``dim``.

    ``forward``: ImageNet-normalised ``[B, 3, H, W]`` -> L2-normalised ``[B, dim]``;
    ``feature_map``: the same input -> ``layer4`` (default; what GeM pools, before the
    per-position L2) or any other ResNet layer ``[B, C, h, w]``. State-dict keys are
    the published checkpoints'.
    """

    def __init__(self, backbone: str = DEFAULT_BACKBONE, dim: int = DEFAULT_DIM):
        super().__init__()
        if backbone not in BACKBONES:
            raise ValueError(f"unknown backbone {backbone!r}; expected one of {sorted(BACKBONES)}")
        depth = BACKBONES[backbone]
        self.backbone = nn.Sequential(*ResNet(depth, "layer4").stages())
        channels = resnet_channels(depth, "layer4")
        self.aggregation = nn.Sequential(
            ChannelL2(), GeM(), nn.Flatten(1), nn.Linear(channels, dim), ChannelL2()
        )
        self.backbone_name, self.dim = backbone, dim
        self.input_size, self.mean, self.std = INPUT_SIZE, MEAN, STD

    def feature_map(self, images: torch.Tensor, layer: str = "layer4") -> torch.Tensor:
        return stage_maps(list(self.backbone), images, [layer])[layer]

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.aggregation(self.backbone(images))


def _load(method: str, dims: dict, path: str, backbone: str, dim: int) -> GeoLocalizationNet:
    if backbone not in dims or dim not in dims[backbone]:
        published = {name: list(values) for name, values in dims.items()}
        raise ValueError(
            f"{method} publishes no {backbone} model of dimension {dim}; published: {published}"
        )
    name = f"{method} {backbone}-{dim}"
    hint = trained_model(method.lower()).published(f"{backbone}_{dim}").hint
    model = GeoLocalizationNet(backbone, dim)
    load_matching(model, read_state(path, name, hint), path, name, hint)
    return model.eval()


def load_cosplace(
    path: str, backbone: str = DEFAULT_BACKBONE, dim: int = DEFAULT_DIM
) -> GeoLocalizationNet:
    """CosPlace ``backbone``-``dim`` (:data:`COSPLACE_DIMS`) with the weights of ``path``
    (``<backbone>_<dim>_cosplace.pth``). Raises
    :class:`~vprflow.models.checkpoints.CheckpointError` naming the model, the file, the
    key at fault and the release URL."""
    return _load("CosPlace", COSPLACE_DIMS, path, backbone, dim)


def load_eigenplaces(
    path: str, backbone: str = DEFAULT_BACKBONE, dim: int = DEFAULT_DIM
) -> GeoLocalizationNet:
    """EigenPlaces ``backbone``-``dim`` (:data:`EIGENPLACES_DIMS`) with the weights of
    ``path`` (``<backbone>_<dim>_eigenplaces.pth``); errors as :func:`load_cosplace`."""
    return _load("EigenPlaces", EIGENPLACES_DIMS, path, backbone, dim)
