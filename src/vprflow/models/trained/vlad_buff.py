"""VLAD-BuFF (Khaliq et al., ECCV 2024; github.com/Ahmedest61/VLAD-BuFF, also the
``VLAD-BuFF/`` folder of github.com/AnyLoc/Revisit-Anything): DINOv2-B/14 tokens,
NetVLAD with burst-aware soft assignment, then a whitening PCA, 8192-d at 322 x 322.

Architecture (``hubconf.vlad_buff``: ``vpr_model.VPRModel`` with ``aggregation NETVLAD``,
``antiburst``, ``wpca``; plain torch here):

1. backbone: DINOv2 ViT-B/14 (the torch-hub model, run block by block as VLAD-BuFF's
   ``models/backbones/dinov2.py`` does: all 12 blocks then the final LayerNorm, position
   embeddings interpolated as the original DINOv2 code does), the patch tokens as a map
   ``x`` ``[B, 768, H/14, W/14]`` (CLS dropped);
2. aggregator (:class:`VladBuffAggregator`, ``models/aggregators/aggregation.py``'s
   ``NetVLAD`` with ``antiburst``, 64 clusters): each patch ``x_i`` L2-normalised over
   channels; with the pre-pool PCA (``nv_pca``, the ``192PCA`` model) projected,
   ``x_i <- L2(R (x_i - mu))`` with ``R = pca_rot`` ``[nv_pca, 768]``, ``mu = pca_mean``;
   soft assignment ``a_ki = softmax_k(W_k . x_i)`` (``conv``, a bias-free 1x1
   convolution); burst weights from the patches' self-similarity,
   ``s_ij = -2 + 2 x_i . x_j`` and ``w_i = (sum_j sigmoid(alpha s_ij + beta)) ** p``
   with ``(alpha, beta, p) = ab_params`` (8, 7, 1 before training), and
   ``a_ki <- a_ki / w_i``; ``V_k = sum_i a_ki (x_i - c_k)`` with ``c = centroids``,
   each ``V_k`` L2-normalised, flattened as ``k * D + d`` and L2-normalised:
   ``64 * 768 = 49152``-d (``64 * 192 = 12288`` with ``nv_pca``);
3. whitening (``WPCA``, ``add_pca.py``'s ``Conv2d(K * D, num_pcs, 1)`` on the VLAD as
   a 1 x 1 map): ``L2(U V + b)``, ``[B, num_pcs]``.

The published evaluation (``eval.py``) feeds ``model(images)`` (steps 1-2) to
``model.WPCA`` (step 3); without the whitening (``num_pcs=None``) the descriptor is the
VLAD of step 2, which the same checkpoint holds.

Input: RGB in [0, 1] resized to 322 x 322 and normalised with ImageNet's mean / std:
``eval.py``'s ``input_transform`` (torchvision ``Resize((322, 322), BILINEAR)`` on the
PIL image its datasets open with ``Image.open(path).convert("RGB")``, EXIF ignored;
``ToTensor``; ``Normalize``).

Checkpoints (github.com/ahmedest61/VLAD-BuFF/releases/download/v1.0.0, the files
``hubconf.py`` fetches): ``dnv2_NV_AB_wpca8192_last.ckpt`` (no pre-pool PCA, 8192
whitened dims) and ``dnv2_NV_192PCA_AB_wpca4096_last.ckpt`` (``nv_pca = 192``, 4096
dims), each ``{"num_pcs": n, "state_dict": ...}`` as ``add_pca.py`` saves it, read with
``torch.load(weights_only=True)``: ``backbone.model.<torch-hub DINOv2 name>``,
``aggregator.{centroids, conv.weight, ab_params}`` (and ``pca_mean``, ``pca_rot`` with
the pre-pool PCA), ``WPCA_<n>.0.{weight, bias}`` (``hubconf.py`` renames it ``WPCA.``,
which loads too). Tensors of another float type (``add_pca.py`` computes the whitening
in float64) are read into float32, as the authors' ``load_state_dict`` copies them.
Keys the authors' loaders drop (``loss_fn.``, ``miner.``, another ``WPCA_<m>.``) are
ignored; any other key, or a missing one, is an error naming it.
"""

from __future__ import annotations

import re

import torch
from torch import nn
from torch.nn import functional as F

from vprflow.models.checkpoints import CheckpointError

# The published files' names and where they are (models/kinds.py, with the variants).
from vprflow.models.kinds import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    VLAD_BUFF_RELEASE,
    trained_model,
    vlad_buff_file,
)
from vprflow.models.trunks.dinov2 import DinoV2Tokens, load_backbone_and_head
from vprflow.models.trunks.state_dicts import TRAINING_PREFIXES, load_matching, read_state_dict

MEAN, STD = IMAGENET_MEAN, IMAGENET_STD
INPUT_SIZE = trained_model("vlad_buff").height_width
NUM_CLUSTERS = 64
# AntiBurst's (alpha, beta, p) before training (the authors' --ab_w, --ab_b, --ab_p).
AB_PARAMS = (8.0, 7.0, 1.0)


class VladBuffAggregator(nn.Module):
    """NetVLAD with burst-aware soft assignment (module docstring, step 2):
    ``x [B, C, h, w]`` -> ``[B, num_clusters * D]`` (``D = nv_pca or C``). Parameter
    names are the authors' ``NetVLAD``'s."""

    def __init__(self, dim: int = 768, num_clusters: int = NUM_CLUSTERS, nv_pca: int | None = None):
        super().__init__()
        self.num_clusters, self.nv_pca = num_clusters, nv_pca
        dims = nv_pca or dim
        if nv_pca is not None:
            self.pca_mean = nn.Parameter(torch.zeros(dim))
            self.pca_rot = nn.Parameter(torch.zeros(nv_pca, dim))
        self.conv = nn.Conv2d(dims, num_clusters, kernel_size=1, bias=False)
        self.centroids = nn.Parameter(torch.zeros(num_clusters, dims))
        self.ab_params = nn.Parameter(torch.tensor(AB_PARAMS))
        self.dim = num_clusters * dims

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        batch, _, height, width = x.shape
        x = F.normalize(x, p=2, dim=1).flatten(2)  # [B, C, n]
        if self.nv_pca is not None:
            x = torch.einsum("dc,bcn->bdn", self.pca_rot, x - self.pca_mean[None, :, None])
            x = F.normalize(x, p=2, dim=1)
        assign = self.conv(x.reshape(batch, -1, height, width)).flatten(2)
        assign = F.softmax(assign, dim=1)  # [B, K, n]
        similarity = -2 + 2 * x.transpose(1, 2) @ x  # [B, n, n]
        alpha, beta, power = self.ab_params
        burst = torch.sigmoid(similarity * alpha + beta).sum(-1) ** power  # [B, n]
        assign = assign / burst[:, None, :]
        # sum_i a_ki (x_i - c_k), without the [B, K, D, n] residual tensor.
        vlad = torch.einsum("bkn,bdn->bkd", assign, x)
        vlad = vlad - self.centroids[None] * assign.sum(-1, keepdim=True)
        vlad = F.normalize(vlad, p=2, dim=2).flatten(1)
        return F.normalize(vlad, p=2, dim=1)


class Whitening(nn.Module):
    """``add_pca.py``'s whitening, ``L2(U v + b)``: ``[B, in_dim]`` -> ``[B, num_pcs]``.
    Its one weight sits at index 0 (``WPCA_<n>.0.*``) as the authors' ``Sequential``
    of ``Conv2d(in_dim, num_pcs, 1)``, ``Flatten``, ``L2Norm``."""

    def __init__(self, in_dim: int, num_pcs: int):
        super().__init__()
        self.add_module("0", nn.Conv2d(in_dim, num_pcs, kernel_size=1))

    def forward(self, vlad: torch.Tensor) -> torch.Tensor:
        conv = getattr(self, "0")
        return F.normalize(F.linear(vlad, conv.weight.flatten(1), conv.bias), p=2, dim=-1)


class VladBuff(nn.Module):
    """``forward``: ImageNet-normalised ``[B, 3, H, W]`` (multiples of 14; 322 x 322
    published) -> ``[B, num_pcs]`` (or the ``[B, K * D]`` VLAD when ``num_pcs`` is
    None); ``feature_map``: the same input -> normed patch tokens
    ``[B, 768, H/14, W/14]``."""

    def __init__(
        self,
        config=None,
        *,
        nv_pca: int | None = None,
        num_pcs: int | None = 8192,
        num_clusters: int = NUM_CLUSTERS,
    ):
        super().__init__()
        self.backbone = DinoV2Tokens(config, final_norm=True)
        self.aggregator = VladBuffAggregator(self.backbone.dim, num_clusters, nv_pca)
        self.WPCA = None if num_pcs is None else Whitening(self.aggregator.dim, num_pcs)
        self.num_pcs = num_pcs
        self.dim = self.aggregator.dim if num_pcs is None else num_pcs
        self.input_size, self.mean, self.std = INPUT_SIZE, MEAN, STD

    def feature_map(self, images: torch.Tensor) -> torch.Tensor:
        return self.backbone(images)[0]

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        vlad = self.aggregator(self.backbone(images)[0])
        return vlad if self.WPCA is None else self.WPCA(vlad)


def _load_whitening(model: VladBuff, state: dict, path: str, hint: str) -> None:
    """``WPCA_<num_pcs>.0.*`` (or hubconf's renamed ``WPCA.0.*``) into ``model.WPCA``."""
    names = [p for p in (f"WPCA_{model.num_pcs}.", "WPCA.") if any(k.startswith(p) for k in state)]
    if len(names) != 1:
        found = sorted({m[0] for k in state if (m := re.match(r"WPCA(_\d+)?\.", k))})
        raise CheckpointError(
            f"VLAD-BuFF: checkpoint {path!r} "
            + (
                f"holds both {names[0]!r} and {names[1]!r} whitenings"
                if names
                else f"has no whitening of {model.num_pcs} dims (WPCA_{model.num_pcs}.*; "
                f"whitenings found: {found or 'none'})"
            )
            + f"; {hint}"
        )
    # Under its own name, so that a key at fault is named as the file names it.
    prefix = names[0]
    named = nn.ModuleDict({prefix.rstrip("."): model.WPCA})
    weights = {k: v for k, v in state.items() if k.startswith(prefix)}
    load_matching(named, weights, path, "VLAD-BuFF", hint)


def load_vlad_buff(
    path: str,
    config=None,
    *,
    nv_pca: int | None = None,
    num_pcs: int | None = 8192,
    num_clusters: int = NUM_CLUSTERS,
) -> VladBuff:
    """VLAD-BuFF with the weights of ``path`` (a published checkpoint's layout, module
    docstring): without pre-pool PCA (``nv_pca=None``, ``dnv2_NV_AB_wpca8192_last.ckpt``)
    or with it (``nv_pca=192``, ``dnv2_NV_192PCA_AB_wpca4096_last.ckpt``), whitened to
    ``num_pcs`` dims or, with ``num_pcs=None``, the VLAD itself. ``config`` /
    ``num_clusters`` replace the published sizes (tests). Raises
    :class:`CheckpointError` naming the file, the key at fault and the published URL."""
    model = VladBuff(config, nv_pca=nv_pca, num_pcs=num_pcs, num_clusters=num_clusters)
    file = vlad_buff_file(nv_pca, num_pcs)
    url = VLAD_BUFF_RELEASE + file
    hint = f"expected {file} from {url}"
    state = read_state_dict(path, "VLAD-BuFF", url, file)
    load_backbone_and_head(
        model.backbone,
        model.aggregator,
        state,
        path,
        model_name="VLAD-BuFF",
        backbone_prefixes=("backbone.model.",),
        head_prefix="aggregator.",
        hint=hint,
        # The training module's loss and miner hold no weights of the descriptor; the
        # whitenings are read below (add_pca.py may leave several in one file).
        ignored_prefixes=(*TRAINING_PREFIXES, "WPCA.", "WPCA_"),
    )
    if model.WPCA is not None:
        _load_whitening(model, state, path, hint)
    return model.eval()
