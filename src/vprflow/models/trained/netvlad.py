"""NetVLAD (Arandjelović et al., CVPR 2016): VGG16 conv5_3 + NetVLAD pooling, trained on
Pittsburgh, with the published PyTorch checkpoints of QVPR/Patch-NetVLAD and
Nanne/pytorch-NetVlad.

Architecture (both repositories, plain torch here):

1. ``encoder``: torchvision VGG16 ``features[:29]`` (up to conv5_3, before its ReLU and
   the last pool; :func:`vprflow.models.trunks.vgg.vgg16_features`) -> ``x`` of
   ``[B, 512, h, w]``;
2. ``pool`` (NetVLAD, ``K = 64`` clusters, ``D = 512``): ``x`` L2-normalised over
   channels at every position; soft-assignment ``a = softmax_k(conv_1x1(x))`` (a bias
   only for the "vladv2" initialisation; the published checkpoints are vladv1, without);
   ``V[k] = sum_p a[k, p] * (x[:, p] - centroids[k])``; each ``V[k]`` L2-normalised
   (intra-normalisation), flattened cluster-major (``k * 512 + c``) and L2-normalised:
   ``[B, 32768]``;
3. optional ``WPCA`` (Patch-NetVLAD's whitening PCA, a 1x1 convolution 32768 -> P with
   bias, applied to the descriptor as a ``[B, 32768, 1, 1]`` map) then L2: ``[B, P]``.

Input: RGB in [0, 1] normalised with ImageNet's mean / std; both repositories evaluate
Pittsburgh at its native 480 x 640 (Patch-NetVLAD resizes every image to 480 x 640).

Checkpoints (``torch.load(weights_only=True)``; a dict whose ``state_dict`` holds
``encoder.<i>.{weight,bias}`` for the 13 convolutions, ``pool.centroids`` ``[K, 512]``,
``pool.conv.weight`` ``[K, 512, 1, 1]`` and, for the whitened ones, ``WPCA.0.weight``
``[P, 32768, 1, 1]`` / ``WPCA.0.bias`` ``[P]``). A ``module.`` path component
(``nn.DataParallel``) is ignored. The variants (:data:`VARIANTS`):

- ``patchnetvlad-pitts30k-4096`` (default): Patch-NetVLAD's ``pitts_WPCA4096.pth.tar``,
  4096-d whitened: the NetVLAD Patch-NetVLAD's tables report, a PyTorch model;
- ``patchnetvlad-pitts30k-32768``: the same file without the whitening (32768-d);
- ``patchnetvlad-pitts30k-512`` / ``-128``: ``pitts_WPCA512`` / ``pitts_WPCA128``;
- ``nanne-pitts30k``: Nanne/pytorch-NetVlad's ``vgg16_netvlad_checkpoint``
  (``checkpoints/checkpoint.pth.tar``), 32768-d, no whitening.

Not here: the NetVLAD authors' MATLAB model, which gmberton/VPR-methods-evaluation loads
for ``--method netvlad`` (hloc's port, ``vpr_models/netvlad.py``): the VGG16 Pittsburgh
30k network of Relja/netvlad, ``Pitts30K_struct.mat`` converted at load time, read as
0-255 pixels minus the MATLAB model's ``averageImage`` (std 1), 4096-d through the
MATLAB model's own whitening by default (32768-d without). Other weights, another input
normalisation and another whitening: its descriptors and recalls are not these.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from vprflow.models.checkpoints import CheckpointError, read_checkpoint
from vprflow.models.kinds import IMAGENET_MEAN, IMAGENET_STD, TrainedVariant, trained_model
from vprflow.models.trunks.state_dicts import load_matching
from vprflow.models.trunks.vgg import VGG16_DIM, vgg16_features

NUM_CLUSTERS = 64
MEAN, STD = IMAGENET_MEAN, IMAGENET_STD
# The published files (models/kinds.py's entry), with what each variant reads of its file.
ENTRY = trained_model("netvlad")
INPUT_SIZE = ENTRY.height_width


@dataclass(frozen=True)
class NetVLADVariant:
    """A published variant: its file (name, where to get it, its repository), whether its
    whitening is applied, and the descriptor length that results."""

    published: TrainedVariant
    whitening: bool
    dim: int


# Variant -> the whitened length, or None for the VLAD before the whitening.
_WHITENED = {
    "patchnetvlad-pitts30k-4096": 4096,
    "patchnetvlad-pitts30k-32768": None,
    "patchnetvlad-pitts30k-512": 512,
    "patchnetvlad-pitts30k-128": 128,
    "nanne-pitts30k": None,
}
VARIANTS = {
    name: NetVLADVariant(
        published, _WHITENED[name] is not None, _WHITENED[name] or NUM_CLUSTERS * VGG16_DIM
    )
    for name, published in ENTRY.variants.items()
}
DEFAULT_VARIANT = ENTRY.default_variant

# Nanne's training script stores numpy scalars (recalls, best score) beside the state
# dict; these globals rebuild such scalars and nothing else.
_NUMPY_GLOBALS = [
    np.dtype,
    np.dtypes.Float64DType,
    np.dtypes.Float32DType,
    np.dtypes.Int64DType,
    getattr(np, "_core", getattr(np, "core", None)).multiarray.scalar,
]


class NetVLADPooling(nn.Module):
    """NetVLAD over a ``[B, D, h, w]`` map -> ``[B, K * D]`` (see the module docstring).

    Parameters ``conv`` (``Conv2d(D, K, 1)``, bias only when ``bias``) and
    ``centroids`` ``[K, D]``, named as in both original repositories.
    """

    def __init__(self, num_clusters: int = NUM_CLUSTERS, dim: int = VGG16_DIM, bias: bool = False):
        super().__init__()
        self.num_clusters, self.dim = num_clusters, dim
        self.conv = nn.Conv2d(dim, num_clusters, kernel_size=1, bias=bias)
        self.centroids = nn.Parameter(torch.zeros(num_clusters, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.normalize(x, p=2, dim=1)
        assign = F.softmax(self.conv(x).flatten(2), dim=1)  # [B, K, P]
        points = x.flatten(2)  # [B, D, P]
        # sum_p a[k,p] (x_p - c_k) = sum_p a[k,p] x_p - (sum_p a[k,p]) c_k
        vlad = torch.einsum("bkp,bdp->bkd", assign, points)
        vlad = vlad - assign.sum(dim=2).unsqueeze(-1) * self.centroids.unsqueeze(0)
        vlad = F.normalize(vlad, p=2, dim=2)
        return F.normalize(vlad.flatten(1), p=2, dim=1)


class NetVLADModel(nn.Module):
    """VGG16 conv5_3 + NetVLAD (+ whitening PCA to ``num_pcs`` when given).

    ``forward``: ImageNet-normalised ``[B, 3, H, W]`` -> L2-normalised ``[B, dim]``;
    ``feature_map``: the same input -> conv5_3 ``[B, 512, H/16, W/16]`` (what the pooling
    sees before its per-position normalisation). State-dict keys are the checkpoints'.
    """

    def __init__(
        self,
        num_clusters: int = NUM_CLUSTERS,
        num_pcs: int | None = 4096,
        *,
        encoder: nn.Module | None = None,
        encoder_dim: int = VGG16_DIM,
        vlad_bias: bool = False,
    ):
        super().__init__()
        # Tests pass a smaller encoder; the published models all use VGG16 conv5_3.
        self.encoder = vgg16_features("conv5_3") if encoder is None else encoder
        self.pool = NetVLADPooling(num_clusters, encoder_dim, bias=vlad_bias)
        self.num_pcs = num_pcs
        if num_pcs:
            self.WPCA = nn.Sequential(nn.Conv2d(num_clusters * encoder_dim, num_pcs, 1))
        self.dim = int(num_pcs or num_clusters * encoder_dim)
        self.input_size, self.mean, self.std = INPUT_SIZE, MEAN, STD

    def feature_map(self, images: torch.Tensor) -> torch.Tensor:
        return self.encoder(images)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        vlad = self.pool(self.encoder(images))
        if not self.num_pcs:
            return vlad
        whitened = self.WPCA[0](vlad[:, :, None, None]).flatten(1)
        return F.normalize(whitened, p=2, dim=-1)


def _strip_parallel(key: str) -> str:
    return re.sub(r"(^|\.)module\.", r"\1", key)


def _read(path: str, name: str, variant: NetVLADVariant) -> dict[str, torch.Tensor]:
    published = variant.published
    hint = f"download {published.file} ({published.repository}) from {published.url}"
    try:
        with torch.serialization.safe_globals(_NUMPY_GLOBALS):
            checkpoint = read_checkpoint(path)
    except CheckpointError as error:
        raise CheckpointError(f"NetVLAD {name!r}: {error}; {hint}") from error
    state = checkpoint.get("state_dict", checkpoint) if isinstance(checkpoint, dict) else None
    if not isinstance(state, dict) or "pool.centroids" not in {
        _strip_parallel(k) for k in state if isinstance(k, str)
    }:
        raise CheckpointError(
            f"NetVLAD {name!r}: checkpoint {path!r} has no 'state_dict' with 'pool.centroids' "
            f"(the Patch-NetVLAD / pytorch-NetVlad layout); {hint}"
        )
    return {_strip_parallel(k): v for k, v in state.items() if isinstance(k, str)}


def load_netvlad(
    path: str, variant: str = DEFAULT_VARIANT, *, encoder: nn.Module | None = None
) -> NetVLADModel:
    """The NetVLAD ``variant`` (:data:`VARIANTS`) with the weights of checkpoint ``path``.

    Raises :class:`CheckpointError` naming the variant, the file, the key at fault and
    the checkpoint's URL when the file is absent, unreadable or of another layout.
    ``encoder`` replaces VGG16 (tests use a small one; its keys must match the file's).
    """
    if variant not in VARIANTS:
        raise ValueError(f"unknown NetVLAD variant {variant!r}; expected one of {sorted(VARIANTS)}")
    spec = VARIANTS[variant]
    state = _read(path, variant, spec)
    hint = spec.published.hint
    clusters, encoder_dim = state["pool.centroids"].shape
    if spec.whitening and "WPCA.0.weight" not in state:
        raise CheckpointError(
            f"NetVLAD {variant!r}: checkpoint {path!r} has no whitening ('WPCA.0.weight'); {hint}"
        )
    num_pcs = int(state["WPCA.0.weight"].shape[0]) if spec.whitening else None
    vlad_bias = "pool.conv.bias" in state  # a "vladv2" model; the published ones are not
    model = NetVLADModel(
        clusters, num_pcs, encoder=encoder, encoder_dim=encoder_dim, vlad_bias=vlad_bias
    )
    if encoder is None and (clusters, encoder_dim) != (NUM_CLUSTERS, VGG16_DIM):
        raise CheckpointError(
            f"NetVLAD {variant!r}: checkpoint {path!r} key 'pool.centroids' has shape "
            f"{tuple(state['pool.centroids'].shape)}, expected {(NUM_CLUSTERS, VGG16_DIM)}; {hint}"
        )
    if encoder is None and model.dim != spec.dim:
        raise CheckpointError(
            f"NetVLAD {variant!r}: checkpoint {path!r} gives {model.dim}-d descriptors "
            f"('WPCA.0.weight' {tuple(state['WPCA.0.weight'].shape)}), expected {spec.dim}; {hint}"
        )
    # A whitening in the file of an unwhitened variant is left out, not refused.
    ignore = () if spec.whitening else ("WPCA.",)
    load_matching(model, state, path, f"NetVLAD {variant!r}", hint, ignore=ignore)
    return model.eval()
