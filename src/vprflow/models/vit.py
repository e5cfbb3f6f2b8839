"""Dense patch features from DINOv2 / DINOv3 / DINO (v1) vision transformers via transformers.

``load_vit(params, device)`` returns a :class:`VitBackbone` whose ``features`` maps a
float image batch ``[B, H, W, 3]`` in ``[0, 1]`` to patch descriptors ``[B, h, w, D]``:

1. centre-crop H, W down to multiples of the patch size (same offsets as torchvision's
   ``CenterCrop``, which AnyLoc uses: ``round((H - h*p) / 2)``);
2. mean/std normalisation: ImageNet's, except for DINOv3, whose mean/std come from the
   model directory's ``preprocessor_config.json`` (``image_mean`` / ``image_std``) when
   it has one (the satellite ``*-sat493m`` models use other statistics) and are
   ImageNet's otherwise (the web ``*-lvd1689m`` models' processor defaults);
3. forward pass up to block ``layer`` (blocks after it are dropped from the loaded
   model, so DINOv2-G at layer 31 runs 32 of its 40 blocks);
4. a forward hook takes the facet: ``query`` / ``key`` / ``value`` are the outputs of
   the block's attention q / k / v projections, which transformers applies to the
   block's normed input ``norm1(hidden)`` (the three thirds of the original ``qkv``
   Linear). For DINOv3 these are taken before RoPE: the rotation transformers applies
   afterwards to the patch tokens' queries and keys is not in the facet, so ``query`` /
   ``key`` are the projections' outputs exactly as for DINOv2 (and position-independent
   linear maps of the normed input); ``token`` is the block's output hidden state,
   optionally followed by the model's final LayerNorm (``final_norm``, what SNSM uses
   on DINO's last block, and SegVLAD-FineT on its fine-tuned DINOv2's);
5. prefix tokens (CLS and any register tokens) are dropped: the patch tokens are the
   last ``h*w`` tokens of the sequence;
6. optional per-patch L2 normalisation over channels (``normalize``).

DINOv3 has no learned position embeddings: RoPE is computed for each input's patch
grid, so ``pos_embed_interpolation`` does not apply and a DINOv3 entry that sets it is
refused. Otherwise position embeddings are interpolated for any input size: DINOv2
models always do it, ``ViTModel`` (DINO v1) is called with
``interpolate_pos_encoding=True``. The rule is chosen by ``pos_embed_interpolation``
(``POS_EMBED_INTERPOLATIONS``):

- ``"original"`` (default): as the original facebookresearch/dinov2 and dino code does
  it. The stored ``M x M`` grid of patch position embeddings (``M = sqrt(N)``) is
  resized bicubically (``align_corners=False``, no antialiasing, in float32) with
  ``scale_factor = ((rows + 0.1) / M, (cols + 0.1) / M)``, where ``rows`` x ``cols`` is
  the input's patch grid (the original code calls the input's height ``w``, but the row
  factor does come from the height), and flattened row by row. Output
  position ``r`` therefore samples the grid at ``(r + 0.5) * M / (rows + 0.1) - 0.5``,
  not at ``(r + 0.5) * M / rows - 0.5``. With ``N`` patches and a square input the
  stored embeddings are used unchanged. The loaded model's embeddings module gets this
  as its ``interpolate_pos_encoding`` (on that instance only). DINOv2 with registers is
  left as transformers builds it: the original ``*_reg`` models interpolate to the
  output size with antialiasing (no 0.1 offset), which is what transformers does.
- ``"transformers"``: transformers' own method, bicubic to ``size=(rows, cols)``.
"""

from __future__ import annotations

import inspect
import json
import math
import types
from pathlib import Path

import numpy as np
import torch
from torch import nn
from transformers import AutoConfig, AutoModel

from vprflow.core.arrays import center_crop_box
from vprflow.core.devices import resolve_device, resolve_dtype
from vprflow.models.checkpoints import load_hub_checkpoint
from vprflow.models.hub import load_pretrained, resolve_model_source
from vprflow.models.kinds import (
    BACKBONES,
    FACETS,
    IMAGENET_MEAN,
    IMAGENET_STD,
    POS_EMBED_INTERPOLATIONS,
    VitFamily,
    with_defaults,
)

# Backbone kind -> its VitFamily: the ViT entries of models/kinds.py, each kind named there once.
VIT_FAMILIES = {
    name: kind.spec for name, kind in BACKBONES.items() if isinstance(kind.spec, VitFamily)
}
# Model type -> whether "original" replaces its interpolation, over every family.
_ORIGINAL_INTERPOLATION = {
    model_type: replaced
    for family in VIT_FAMILIES.values()
    if not family.rope
    for model_type, replaced in family.model_types.items()
}
# Submodule names of the q/k/v projections: transformers >= 5 ("q_proj") and the
# older layout ("attention.attention.query") that transformers 4.x builds.
_FACET_LINEARS = {
    "query": ("q_proj", "query"),
    "key": ("k_proj", "key"),
    "value": ("v_proj", "value"),
}
_BLOCK_LISTS = ("encoder.layer", "layers", "encoder.layers", "model.layer")
# The final LayerNorm: Dinov2Model / ViTModel call it `layernorm`, DINOv3ViTModel `norm`.
_FINAL_NORMS = ("layernorm", "norm")
PREPROCESSOR_CONFIG = "preprocessor_config.json"


def _find_blocks(model: nn.Module) -> tuple[nn.Module, str, nn.ModuleList]:
    """``(parent, attribute, blocks)`` of the transformer block list."""
    for dotted in _BLOCK_LISTS:
        parent_path, _, attribute = dotted.rpartition(".")
        try:
            parent = model.get_submodule(parent_path) if parent_path else model
        except AttributeError:
            continue
        blocks = getattr(parent, attribute, None)
        if isinstance(blocks, nn.ModuleList) and len(blocks) > 0:
            return parent, attribute, blocks
    raise ValueError(f"{type(model).__name__}: cannot find its transformer block list")


def _find_projection(block: nn.Module, facet: str) -> nn.Linear:
    """The Linear of ``block``'s attention that produces the ``facet`` third of qkv."""
    names = _FACET_LINEARS[facet]
    for name, module in block.named_modules():
        leaf = name.rpartition(".")[2]
        if leaf in names and "attention" in name and isinstance(module, nn.Linear):
            return module
    raise ValueError(f"{type(block).__name__}: no attention projection {names} for {facet!r}")


def _check_pos_embed_interpolation(value: str) -> str:
    value = str(value).lower()
    if value not in POS_EMBED_INTERPOLATIONS:
        raise ValueError(
            f"unknown pos_embed_interpolation {value!r}; expected one of {POS_EMBED_INTERPOLATIONS}"
        )
    return value


def _original_interpolate_pos_encoding(
    self: nn.Module, embeddings: torch.Tensor, height: int, width: int
) -> torch.Tensor:
    """Position embeddings for ``embeddings`` (CLS + patch tokens) of a ``height`` x
    ``width`` pixel input, interpolated like the original DINO / DINOv2 code (see the
    module docstring). Bound to a transformers embeddings module, whose
    ``interpolate_pos_encoding(embeddings, height, width)`` it replaces."""
    stored = self.position_embeddings
    num_patches = embeddings.shape[1] - 1
    num_positions = stored.shape[1] - 1
    if num_patches == num_positions and height == width:
        return stored
    side = math.isqrt(num_positions)
    if side * side != num_positions:
        raise ValueError(f"{num_positions} patch position embeddings do not form a square grid")
    patch = self.patch_embeddings.patch_size
    patch_h, patch_w = patch if isinstance(patch, list | tuple) else (patch, patch)
    rows, cols = height // patch_h, width // patch_w
    dim = stored.shape[-1]
    grid = stored[:, 1:].float().reshape(1, side, side, dim).permute(0, 3, 1, 2)
    grid = nn.functional.interpolate(
        grid,
        scale_factor=((rows + 0.1) / side, (cols + 0.1) / side),
        mode="bicubic",
        align_corners=False,
        antialias=False,
        recompute_scale_factor=False,
    )
    if tuple(grid.shape[-2:]) != (rows, cols):
        raise RuntimeError(f"interpolated a {tuple(grid.shape[-2:])} grid for {(rows, cols)}")
    patches = grid.permute(0, 2, 3, 1).reshape(1, rows * cols, dim)
    return torch.cat((stored[:, :1].float(), patches), dim=1).to(embeddings.dtype)


def _set_pos_embed_interpolation(model: nn.Module, interpolation: str) -> None:
    """Give ``model``'s embeddings the original interpolation if asked and needed."""
    if interpolation == "transformers":
        return
    model_type = getattr(model.config, "model_type", None)
    if model_type not in _ORIGINAL_INTERPOLATION:
        raise ValueError(
            f"pos_embed_interpolation 'original' is not implemented for {model_type!r} "
            f"models (only {sorted(_ORIGINAL_INTERPOLATION)}); use 'transformers'"
        )
    if not _ORIGINAL_INTERPOLATION[model_type]:
        return
    embeddings = getattr(model, "embeddings", None)
    if not all(
        hasattr(embeddings, name)
        for name in ("position_embeddings", "patch_embeddings", "interpolate_pos_encoding")
    ):
        raise ValueError(
            f"{type(model).__name__}: its embeddings lack position_embeddings, "
            "patch_embeddings or interpolate_pos_encoding; cannot replace the interpolation"
        )
    embeddings.interpolate_pos_encoding = types.MethodType(
        _original_interpolate_pos_encoding, embeddings
    )


def _resolve_layer(layer: int, n_blocks: int) -> int:
    index = int(layer) + n_blocks if int(layer) < 0 else int(layer)
    if not 0 <= index < n_blocks:
        raise ValueError(
            f"layer {layer} is out of range for a model with {n_blocks} blocks "
            f"(0..{n_blocks - 1}, or negative from the end); set the `layer` parameter"
        )
    return index


class VitBackbone:
    """A loaded ViT tapped at one block and facet; see the module docstring.

    Attributes: ``patch_size`` (pixels per patch side), ``layer`` (0-based block),
    ``facet``, ``dim`` (descriptor length D), ``device``, ``dtype``,
    ``pos_embed_interpolation`` (``None`` for RoPE models), ``mean`` / ``std`` (the
    per-channel normalisation). ``"original"`` replaces the interpolation method of
    ``model``'s embeddings module in place.
    """

    def __init__(
        self,
        model: nn.Module,
        *,
        layer: int,
        facet: str,
        normalize: bool,
        final_norm: bool,
        device: torch.device,
        dtype: torch.dtype,
        pos_embed_interpolation: str | None = "original",
        mean: tuple[float, float, float] = IMAGENET_MEAN,
        std: tuple[float, float, float] = IMAGENET_STD,
    ):
        self.pos_embed_interpolation = None
        if pos_embed_interpolation is not None:
            self.pos_embed_interpolation = _check_pos_embed_interpolation(pos_embed_interpolation)
            _set_pos_embed_interpolation(model, self.pos_embed_interpolation)
        parent, attribute, blocks = _find_blocks(model)
        # Blocks after `layer` never influence the tapped output: drop them to save
        # time and memory (this model object is private to the backbone).
        setattr(parent, attribute, nn.ModuleList(list(blocks)[: layer + 1]))
        block = blocks[layer]
        self.model = model.eval().requires_grad_(False)
        self.tap = block if facet == "token" else _find_projection(block, facet)
        self.norm = None
        if final_norm:
            norms = (getattr(model, name, None) for name in _FINAL_NORMS)
            self.norm = next((n for n in norms if isinstance(n, nn.LayerNorm)), None)
            if self.norm is None:
                raise ValueError(f"{type(model).__name__} has no final LayerNorm {_FINAL_NORMS}")
        patch = model.config.patch_size
        self.patch_size = int(patch[0] if isinstance(patch, list | tuple) else patch)
        self.layer, self.facet, self.normalize = layer, facet, normalize
        self.dim = int(self.tap.out_features if facet != "token" else model.config.hidden_size)
        self.device, self.dtype = device, dtype
        accepts = inspect.signature(model.forward).parameters
        # ViTModel only interpolates position embeddings when asked; DINOv2 always does
        # and must not receive the keyword (its **kwargs reach the attention kernels).
        self._forward_kwargs = (
            {"interpolate_pos_encoding": True} if "interpolate_pos_encoding" in accepts else {}
        )
        self.mean, self.std = tuple(mean), tuple(std)
        self._mean = torch.tensor(self.mean, device=device).view(1, 3, 1, 1)
        self._std = torch.tensor(self.std, device=device).view(1, 3, 1, 1)

    def features(self, batch: np.ndarray) -> np.ndarray:
        """float32 ``[B, H, W, 3]`` in ``[0, 1]`` -> float32 ``[B, H//p, W//p, D]``."""
        images = np.asarray(batch, dtype=np.float32)
        if images.ndim != 4 or images.shape[3] != 3:
            raise ValueError(f"expected a batch [B, H, W, 3], got shape {images.shape}")
        count, height, width, _ = images.shape
        top, left, crop_h, crop_w = center_crop_box(height, width, self.patch_size)
        images = np.ascontiguousarray(images[:, top : top + crop_h, left : left + crop_w])
        grid_h, grid_w = crop_h // self.patch_size, crop_w // self.patch_size

        captured: list[torch.Tensor] = []

        def grab(_module, _inputs, output):
            captured.append(output[0] if isinstance(output, tuple) else output)

        handle = self.tap.register_forward_hook(grab)
        try:
            with torch.inference_mode():
                pixels = torch.from_numpy(images).to(self.device).permute(0, 3, 1, 2)
                pixels = ((pixels - self._mean) / self._std).to(self.dtype)
                self.model(pixel_values=pixels, **self._forward_kwargs)
                tokens = captured[-1]
                if self.norm is not None:
                    tokens = self.norm(tokens)
                # Prefix tokens (CLS, registers) come first; patches are the tail.
                patches = tokens[:, -grid_h * grid_w :, :].float()
                patches = patches.reshape(count, grid_h, grid_w, -1)
                if self.normalize:
                    patches = nn.functional.normalize(patches, dim=-1)
                return patches.cpu().numpy()
        finally:
            handle.remove()


def _read_normalisation(source: str, model_name: str) -> tuple[tuple, tuple]:
    """``(mean, std)`` from ``source``'s ``preprocessor_config.json``, ImageNet's when the
    directory has none (or it names neither)."""
    path = Path(source) / PREPROCESSOR_CONFIG
    if not path.is_file():
        return IMAGENET_MEAN, IMAGENET_STD
    try:
        processor = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise ValueError(f"model {model_name!r}: cannot read {path}: {error}") from error
    values = []
    for name, default in (("image_mean", IMAGENET_MEAN), ("image_std", IMAGENET_STD)):
        value = processor.get(name, default)
        if not (
            isinstance(value, list | tuple)
            and len(value) == 3
            and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
            and (name == "image_mean" or all(v > 0 for v in value))
        ):
            raise ValueError(
                f"model {model_name!r}: {path} has {name} {value!r}; expected 3 numbers"
            )
        values.append(tuple(float(v) for v in value))
    return values[0], values[1]


def load_vit(params: dict, device: str = "auto") -> VitBackbone:
    """Load a DINOv2 (``Dinov2Model``), DINOv3 (``DINOv3ViTModel``) or DINO
    (``ViTModel``) backbone.

    ``params`` keys (others are ignored; ``batch_size`` is the caller's business):
    ``backbone`` ``"dinov2"`` | ``"dinov3"`` | ``"dino"``; ``model`` hub id or local
    directory (defaults ``facebook/dinov2-giant`` /
    ``facebook/dinov3-vitl16-pretrain-lvd1689m`` / ``facebook/dino-vitb8``);
    ``cache_dir``; ``layer`` 0-based block, negative counts from the end (default 31 for
    dinov2, 18 for dinov3, the last block for dino); ``facet``
    ``"query"|"key"|"value"|"token"`` (default ``"value"``); ``normalize`` per-patch L2
    over channels (default ``True``); ``final_norm`` final LayerNorm on the token facet
    (default ``False``); ``dtype`` ``"float32"|"bfloat16"|"float16"`` (default
    ``"float32"``); ``pos_embed_interpolation`` ``"original"|"transformers"`` (default
    ``"original"``, see the module docstring; not for dinov3, which uses RoPE);
    ``checkpoint`` (dinov2 only) a torch-hub-layout state dict file whose weights replace
    the model's (:mod:`vprflow.models.checkpoints`, e.g. SegVLAD-FineT).
    Raises :class:`vprflow.models.hub.ModelNotFoundError` when the weights are unavailable.
    """
    backbone = str(params.get("backbone", "dinov2")).lower()
    if backbone not in VIT_FAMILIES:
        raise ValueError(
            f"unknown ViT backbone {backbone!r}; expected one of {sorted(VIT_FAMILIES)}"
        )
    family = VIT_FAMILIES[backbone]
    params = with_defaults("features", {**params, "backbone": backbone})
    facet = str(params["facet"]).lower()
    if facet not in FACETS:
        raise ValueError(f"unknown facet {facet!r}; expected one of {FACETS}")
    final_norm = bool(params["final_norm"])
    if final_norm and facet != "token":
        raise ValueError(f"final_norm applies to the 'token' facet only, not {facet!r}")
    if family.rope:
        if params.get("pos_embed_interpolation") is not None:
            raise ValueError(
                f"pos_embed_interpolation does not apply to {backbone!r}: its positions are "
                "RoPE, computed for every input's patch grid; remove the key"
            )
        interpolation = None
    else:
        interpolation = _check_pos_embed_interpolation(params["pos_embed_interpolation"])
    checkpoint = params.get("checkpoint")
    if checkpoint is not None and not family.hub_checkpoint:
        takes = " / ".join(repr(name) for name, f in VIT_FAMILIES.items() if f.hub_checkpoint)
        raise ValueError(f"checkpoint applies to the {takes} backbone only, not {backbone!r}")
    torch_device = resolve_device(device)
    dtype = resolve_dtype(params["dtype"], torch_device)

    model_name = params["model"]
    source = resolve_model_source(str(model_name), params.get("cache_dir"))
    config = AutoConfig.from_pretrained(source)
    if config.model_type not in family.model_types:
        raise ValueError(
            f"model {model_name!r} is a {config.model_type!r} model, but backbone "
            f"{backbone!r} expects {tuple(family.model_types)}"
        )
    extra = {} if family.pooler else {"add_pooling_layer": False}
    model, info = load_pretrained(
        AutoModel.from_pretrained,
        source,
        str(model_name),
        dtype=dtype,
        output_loading_info=True,
        **extra,
    )
    # A checkpoint whose names the installed transformers cannot map would otherwise be
    # filled with random weights, and the features would be silently meaningless.
    missing = sorted(info.get("missing_keys") or [])
    if missing:
        raise ValueError(
            f"model {model_name!r} ({source}): the checkpoint lacks {len(missing)} weights "
            f"of the {type(model).__name__} architecture, e.g. {missing[:3]}; it does not "
            "match this transformers version or model type"
        )
    if checkpoint is not None:
        load_hub_checkpoint(model, str(checkpoint))
    model = model.to(torch_device)
    _, _, blocks = _find_blocks(model)
    layer = _resolve_layer(params["layer"], len(blocks))
    mean, std = IMAGENET_MEAN, IMAGENET_STD
    if family.model_normalisation:
        mean, std = _read_normalisation(source, str(model_name))
    return VitBackbone(
        model,
        layer=layer,
        facet=facet,
        normalize=bool(params.get("normalize", True)),
        final_norm=final_norm,
        device=torch_device,
        dtype=dtype,
        pos_embed_interpolation=interpolation,
        mean=mean,
        std=std,
    )
