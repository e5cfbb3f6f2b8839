"""Any trained VPR model as a vprflow backbone.

The trained models (:mod:`vprflow.models.trained`: NetVLAD, SALAD, VLAD-BuFF, BoQ-DINOv2,
MegaLoc, MixVPR, Conv-AP, BoQ-ResNet50, CosPlace, EigenPlaces; the kinds of
:data:`vprflow.models.kinds.TRAINED_KINDS`) are plain torch modules whose ``forward``
takes ImageNet-normalised ``[B, 3, H, W]`` and returns the model's L2-normalised
descriptor ``[B, D]``, and whose ``feature_map`` returns the dense map their head reads
``[B, C, h, w]``. :class:`TrainedBackbone` gives
them the interface of :mod:`vprflow.models.backbones` (``patch_size``, ``features`` of
``[B, H, W, 3]`` float32 in [0, 1] -> ``[B, h, w, D]``), so that the features stage
runs them like any other backbone:

- ``output: descriptor``: the descriptor as a 1 x 1 grid (``[B, 1, 1, D]``), which the
  ``model`` aggregator reads as the image's descriptor;
- ``output: features``: the dense map, channels last, for AnyLoc-VLAD, SegVLAD, SNSM,
  pooling and re-ranking.

Each kind's entry (:class:`vprflow.models.kinds.TrainedModel`) names its published
checkpoints, its input size (the
entry's default ``resolution``: the features stage resizes to it, as the published
reader does, before the model sees the image) and the stride of its map.
"""

from __future__ import annotations

import numpy as np
import torch

from vprflow.core.arrays import center_crop_box, l2_normalize
from vprflow.core.devices import resolve_device
from vprflow.models.checkpoints import CheckpointError
from vprflow.models.kinds import (
    IMAGENET_MEAN,
    IMAGENET_STD,
    TRAINED_OUTPUTS,
    TrainedModel,
    model_kind,
    with_defaults,
)


class TrainedBackbone:
    """A trained model behind the backbone interface (module docstring).

    ``model``: the loaded module (``forward``, ``feature_map``, ``mean``, ``std``);
    ``output``: :data:`~vprflow.models.kinds.TRAINED_OUTPUTS`; ``patch_size``: the
    stride of its ``feature_map``; ``crop``: centre-crop inputs to whole patches first
    (the DINOv2 models need multiples of 14; vprflow's ViT backbones crop the same way);
    ``normalize``: L2-normalise each stored vector (the descriptors already are, up to
    rounding); ``layer``: the map ``feature_map`` returns (``"layer<k>"``), for a trunk
    that offers several (ResNet-50); ``None``: the model's own.
    """

    def __init__(
        self,
        model: torch.nn.Module,
        output: str,
        patch_size: int,
        *,
        crop: bool,
        normalize: bool = True,
        device: str | torch.device = "auto",
        layer: str | None = None,
    ):
        if output not in TRAINED_OUTPUTS:
            raise ValueError(f"unknown output {output!r}; expected one of {TRAINED_OUTPUTS}")
        self.device = resolve_device(str(device)) if isinstance(device, str) else device
        self.model = model.to(self.device).eval()
        self.output, self.patch_size = output, patch_size
        self.crop, self.normalize = crop, normalize
        shape = (1, 3, 1, 1)
        # A plain ImageNet trunk (resnet50) states no mean / std: ImageNet's.
        mean, std = getattr(model, "mean", IMAGENET_MEAN), getattr(model, "std", IMAGENET_STD)
        self.mean = torch.tensor(mean, dtype=torch.float32, device=self.device).view(shape)
        self.std = torch.tensor(std, dtype=torch.float32, device=self.device).view(shape)
        self.layer = layer

    def preprocess(self, batch: np.ndarray) -> torch.Tensor:
        """``[B, H, W, 3]`` float32 in [0, 1] -> the model's input: centre-cropped to
        whole patches when ``crop``, channels first, ImageNet-normalised (torchvision's
        ``ToTensor`` then ``Normalize``, as every published evaluation does)."""
        if self.crop:
            top, left, height, width = center_crop_box(
                batch.shape[1], batch.shape[2], self.patch_size
            )
            batch = batch[:, top : top + height, left : left + width]
        pixels = torch.from_numpy(np.ascontiguousarray(batch, dtype=np.float32))
        # Contiguous channels first, as ToTensor gives: the permuted view is channels-last
        # in memory, on which a ResNet's convolutions take other kernels (2.4e-4 apart at
        # layer 3 with published weights).
        pixels = pixels.to(self.device).permute(0, 3, 1, 2).contiguous()
        return (pixels - self.mean) / self.std

    @torch.inference_mode()
    def features(self, batch: np.ndarray) -> np.ndarray:
        """float32 ``[B, 1, 1, D]`` (descriptor) or ``[B, h, w, C]`` (features)."""
        pixels = self.preprocess(batch)
        if self.output == "descriptor":
            grids = self.model(pixels)[:, None, None, :]
        else:
            extra = {} if self.layer is None else {"layer": self.layer}
            grids = self.model.feature_map(pixels, **extra).permute(0, 2, 3, 1)
        grids = grids.float().cpu().numpy()
        return l2_normalize(grids) if self.normalize else grids


def load_trained(params: dict, load_model, device: str = "auto") -> TrainedBackbone:
    """A :class:`TrainedBackbone` from a trained kind's backbone entry: ``backbone``
    (one of :data:`~vprflow.models.kinds.TRAINED_KINDS`), ``checkpoint`` (the published
    file), ``variant``, ``output``, ``normalize``; ``load_model(checkpoint path,
    **variant loader_options)`` builds the model
    (:data:`vprflow.models.loaders.TRAINED_MODELS`). A missing ``checkpoint`` raises
    :class:`CheckpointError` naming the model, the file its variant expects and where to
    get it (the plan refuses it earlier, with the same words; the model's loader names a
    file of another layout)."""
    kind = model_kind("features", params)
    spec = kind.spec
    if not isinstance(spec, TrainedModel):
        raise ValueError(f"backbone {kind.name!r} is not a trained model")
    params = with_defaults("features", params)
    variant = params["variant"]
    if variant not in spec.variants:
        raise ValueError(
            f"backbone {kind.name!r}: unknown variant {variant!r}; expected one of "
            f"{list(spec.variants)}"
        )
    published = spec.variants[variant]
    if params.get("checkpoint") is None:
        raise CheckpointError(
            f"backbone {kind.name!r} (variant {variant!r}) needs `checkpoint`: "
            f"{published.file} ({published.repository}), from {published.url}"
        )
    options, layer, patch_size = dict(published.loader_options), None, spec.patch_size
    if spec.layer_strides:
        # A trunk read at `layer`: built only up to it (load_resnet's `end`).
        layer, patch_size = f"layer{params['layer']}", spec.layer_strides[params["layer"]]
        options["end"] = layer
    if params["output"] == "descriptor" and not spec.descriptor:
        raise ValueError(f"backbone {kind.name!r} has no descriptor of its own; output: features")
    model = load_model(str(params["checkpoint"]), **options)
    return TrainedBackbone(
        model,
        params["output"],
        patch_size,
        crop=spec.crop,
        normalize=bool(params.get("normalize", True)),
        device=device,
        layer=layer,
    )
