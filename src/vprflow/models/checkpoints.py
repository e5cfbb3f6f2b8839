"""DINOv2 weights saved in the torch-hub (facebookresearch/dinov2) layout, loaded into
transformers' ``Dinov2Model``.

SegVLAD-FineT (Revisit-Anything) fine-tunes the last blocks of the torch-hub DINOv2
ViT-B/14 with a NetVLAD head and publishes a PyTorch Lightning checkpoint
(``DnV2_NV/last.ckpt``). Its ``state_dict`` holds the backbone as
``backbone.model.<hub name>`` next to the head's ``aggregator.*``; the hub names are
``cls_token``, ``pos_embed``, ``mask_token``, ``register_tokens`` (``*_reg`` models),
``patch_embed.proj.*``, ``blocks.<i>.{norm1, attn.qkv, attn.proj, ls1.gamma, norm2,
mlp.fc1, mlp.fc2 | mlp.w12, mlp.w3, ls2.gamma}.*`` and ``norm.*``. The Revisit-Anything
code reads the backbone's output after its final ``norm`` (``norm_layer=True``).

:func:`load_hub_checkpoint` reads such a file with ``torch.load(weights_only=True)``
(plain tensors and containers; the argparse ``Namespace`` / Lightning ``AttributeDict``
of a Lightning checkpoint's hyper-parameters are unpickled as inert stand-ins, any other
object is refused, naming it), finds the backbone's keys by the unique key that ends in
``patch_embed.proj.weight`` (its prefix, e.g. ``backbone.model.``, is stripped; keys
outside it are ignored), maps them onto the model's own names (the fused ``qkv`` is
split into the q / k / v projections, ``ls1.gamma`` becomes ``layer_scale1.lambda1``,
``norm`` the final ``layernorm``, a fused SwiGLU ``w12`` the gate / up projections) and
replaces every weight of the model. A weight the model has and the file lacks (except
``mask_token``, unused without masking), a key it cannot place or a shape that differs
is a :class:`CheckpointError` naming the file and the keys.
"""

from __future__ import annotations

import os
import re

import torch
from torch import nn

_PATCH_KEY = "patch_embed.proj.weight"
# Where a checkpoint file may keep the state dict: Lightning's "state_dict", DINOv2
# training's "teacher" / "model", or the file itself.
_CONTAINERS = ("state_dict", "teacher", "model")
_OPTIONAL = {"embeddings.mask_token"}  # unused at inference (no masked patches)
_BLOCK = re.compile(r"^blocks\.(?:\d+\.)?(\d+)\.(.+)$")  # also chunked "blocks.<c>.<i>."
_TOP_LEVEL = {
    "cls_token": "embeddings.cls_token",
    "pos_embed": "embeddings.position_embeddings",
    "mask_token": "embeddings.mask_token",
    "register_tokens": "embeddings.register_tokens",
    "patch_embed.proj.weight": "embeddings.patch_embeddings.projection.weight",
    "patch_embed.proj.bias": "embeddings.patch_embeddings.projection.bias",
    "norm.weight": "layernorm.weight",
    "norm.bias": "layernorm.bias",
}
_BLOCK_NAMES = {
    "norm1": "norm1",
    "norm2": "norm2",
    "ls1.gamma": "layer_scale1.lambda1",
    "ls2.gamma": "layer_scale2.lambda1",
    "mlp.fc1": "mlp.fc1",
    "mlp.fc2": "mlp.fc2",
}
# (q, k, v, output) projection names: transformers >= 5, then 4.x.
_ATTENTION_NAMES = (
    ("attention.q_proj", "attention.k_proj", "attention.v_proj", "attention.o_proj"),
    (
        "attention.attention.query",
        "attention.attention.key",
        "attention.attention.value",
        "attention.output.dense",
    ),
)
# SwiGLU: transformers >= 5 splits the fused w12 into gate / up; 4.x keeps it fused.
_SWIGLU_NAMES = (
    ("mlp.gate_proj", "mlp.up_proj", "mlp.down_proj"),
    ("mlp.weights_in", None, "mlp.weights_out"),
)


class CheckpointError(ValueError):
    """A checkpoint file that cannot be read or does not fit the model; names the file."""


class _Inert(dict):
    """Stand-in for the metadata objects of a Lightning checkpoint's hyper-parameters:
    keeps their items and attributes as data, runs none of their code."""

    def __setstate__(self, state):
        if isinstance(state, dict):
            self.update(state)


class _Namespace(_Inert):
    pass


# Objects Lightning pickles into hyper_parameters: (stand-in, the name it is pickled as).
_METADATA_GLOBALS = [
    (_Namespace, "argparse.Namespace"),
    (_Inert, "lightning.fabric.utilities.data.AttributeDict"),
    (_Inert, "pytorch_lightning.utilities.parsing.AttributeDict"),
    (_Inert, "lightning_fabric.utilities.data.AttributeDict"),
]


def read_checkpoint(path: str) -> dict:
    """The object in ``path``, read with ``torch.load(weights_only=True)``."""
    if os.path.isfile(path) and os.path.getsize(path) == 0:  # torch says only "EOFError"
        raise CheckpointError(
            f"checkpoint {path!r} is empty (0 bytes: an interrupted download or copy?): "
            "put the checkpoint there again"
        )
    try:
        with torch.serialization.safe_globals(_METADATA_GLOBALS):
            return torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise CheckpointError(f"checkpoint {path!r} does not exist") from None
    except IsADirectoryError:
        raise CheckpointError(f"checkpoint {path!r} is a folder; it must name a file") from None
    except Exception as error:  # pickle and zip readers raise many types
        unsafe = []
        try:
            unsafe = torch.serialization.get_unsafe_globals_in_checkpoint(path)
        except Exception:  # not a zip checkpoint at all
            pass
        allowed = {name for _, name in _METADATA_GLOBALS}
        unsafe = [name for name in unsafe if name not in allowed]
        if unsafe:
            reason = (
                f"it pickles objects other than tensors and containers ({', '.join(unsafe)}), "
                "which weights_only=True refuses. If you trust the file, save its state "
                "dict alone: torch.save(torch.load(path, weights_only=False)['state_dict'], "
                "new_path)"
            )
        else:
            first = (str(error).strip().splitlines() or [""])[0][:300]
            reason = f"{type(error).__name__}: {first}"
        raise CheckpointError(f"checkpoint {path!r}: cannot read it: {reason}") from error


def backbone_state_dict(checkpoint, path: str) -> tuple[dict[str, torch.Tensor], str]:
    """``(hub-named tensors, stripped prefix)`` of the one DINOv2 backbone in ``checkpoint``."""
    candidates = (
        [checkpoint.get(name) for name in _CONTAINERS] if isinstance(checkpoint, dict) else []
    )
    candidates.append(checkpoint)
    for state in candidates:
        if not isinstance(state, dict):
            continue
        patch_keys = [k for k in state if isinstance(k, str) and k.endswith(_PATCH_KEY)]
        if len(patch_keys) > 1:
            raise CheckpointError(
                f"checkpoint {path!r} holds {len(patch_keys)} DINOv2 backbones "
                f"({', '.join(sorted(patch_keys))}); expected one"
            )
        if patch_keys:
            prefix = patch_keys[0][: -len(_PATCH_KEY)]
            tensors = {
                k[len(prefix) :]: v
                for k, v in state.items()
                if isinstance(k, str) and k.startswith(prefix)
            }
            return tensors, prefix
    raise CheckpointError(
        f"checkpoint {path!r} has no DINOv2 weights in the torch-hub layout "
        f"(no key ending in {_PATCH_KEY!r})"
    )


def _pick(names: tuple, model_keys: set[str]) -> tuple:
    """The first naming scheme whose first projection exists in block 0 of the model."""
    for scheme in names:
        if f"encoder.layer.0.{scheme[0]}.weight" in model_keys:
            return scheme
    return names[0]


def hub_to_transformers(
    hub: dict[str, torch.Tensor], model_keys: set[str]
) -> tuple[dict[str, torch.Tensor], list[str]]:
    """``(tensors under the model's names, hub keys that have no place)``."""
    q, k, v, out = _pick(_ATTENTION_NAMES, model_keys)
    gate, up, down = _pick(_SWIGLU_NAMES, model_keys)
    mapped: dict[str, torch.Tensor] = {}
    unplaced: list[str] = []
    for name, tensor in hub.items():
        if name in _TOP_LEVEL:
            mapped[_TOP_LEVEL[name]] = tensor
            continue
        match = _BLOCK.match(name)
        if not match:
            unplaced.append(name)
            continue
        block, rest = f"encoder.layer.{match[1]}.", match[2]
        module, _, kind = rest.rpartition(".")
        if rest in _BLOCK_NAMES:
            mapped[block + _BLOCK_NAMES[rest]] = tensor
        elif module in _BLOCK_NAMES:
            mapped[f"{block}{_BLOCK_NAMES[module]}.{kind}"] = tensor
        elif module == "attn.qkv" and tensor.shape[0] % 3 == 0:
            for target, part in zip((q, k, v), tensor.chunk(3, dim=0), strict=True):
                mapped[f"{block}{target}.{kind}"] = part
        elif module == "attn.proj":
            mapped[f"{block}{out}.{kind}"] = tensor
        elif module == "mlp.w12" and up is not None and tensor.shape[0] % 2 == 0:
            for target, part in zip((gate, up), tensor.chunk(2, dim=0), strict=True):
                mapped[f"{block}{target}.{kind}"] = part
        elif module == "mlp.w12":
            mapped[f"{block}{gate}.{kind}"] = tensor
        elif module == "mlp.w3":
            mapped[f"{block}{down}.{kind}"] = tensor
        else:
            unplaced.append(name)
    return mapped, unplaced


def _listed(names: list[str], limit: int = 8) -> str:
    shown = ", ".join(names[:limit])
    return shown + (f", ... ({len(names)} in all)" if len(names) > limit else "")


def load_hub_checkpoint(model: nn.Module, path: str) -> dict[str, str]:
    """Replace every weight of the transformers DINOv2 ``model`` with those in ``path``.

    Returns ``{"prefix": ...}``, the key prefix the backbone was found under.
    """
    hub, prefix = backbone_state_dict(read_checkpoint(path), path)
    own = model.state_dict()
    mapped, unplaced = hub_to_transformers(hub, set(own))
    unexpected = sorted(prefix + n for n in unplaced) + sorted(n for n in mapped if n not in own)
    missing = sorted(n for n in own if n not in mapped and n not in _OPTIONAL)
    problems = []
    if missing:
        problems.append(f"missing weights of {type(model).__name__}: {_listed(missing)}")
    if unexpected:
        problems.append(f"unexpected keys: {_listed(unexpected)}")
    shapes = [
        f"{n} {tuple(t.shape)} (model {tuple(own[n].shape)})"
        for n, t in sorted(mapped.items())
        if n in own and tuple(t.shape) != tuple(own[n].shape)
    ]
    if shapes:
        problems.append(f"shapes that differ: {_listed(shapes, 4)}")
    if problems:
        raise CheckpointError(
            f"checkpoint {path!r} (DINOv2 keys under prefix {prefix!r}) does not fit the "
            f"model {getattr(model.config, 'name_or_path', '')!r}: " + "; ".join(problems)
        )
    model.load_state_dict(mapped, strict=False)
    return {"prefix": prefix}
