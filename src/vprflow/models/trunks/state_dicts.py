"""Reading a published state dict and loading it into a model, every error naming the
model, the file, the key at fault and where to get the right file (``hint``): what the
trunks and the trained models share.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path

import torch
from safetensors.torch import load_file
from torch import nn

from vprflow.models.checkpoints import CheckpointError, read_checkpoint

# Lightning-module attributes that may sit beside the model in a training checkpoint
# (the training loss and miner): no weights of the descriptor.
TRAINING_PREFIXES = ("loss_fn.", "miner.")


def read_state(path: str, model_name: str, hint: str, containers: Sequence[str] = ()) -> dict:
    """The state dict in ``path`` (``torch.load(weights_only=True)``), taken from the
    first of ``containers`` (e.g. Lightning's ``"state_dict"``) the file has, else the
    file itself; a :class:`CheckpointError` naming ``model_name``, ``path`` and ``hint``
    when it cannot be read or is not a dict of tensors."""
    try:
        checkpoint = read_checkpoint(path)
    except CheckpointError as error:
        raise CheckpointError(f"{model_name}: {error}; {hint}") from error
    if isinstance(checkpoint, dict):
        for name in containers:
            if isinstance(checkpoint.get(name), dict):
                checkpoint = checkpoint[name]
                break
    if not isinstance(checkpoint, dict) or not any(
        isinstance(v, torch.Tensor) for v in checkpoint.values()
    ):
        raise CheckpointError(
            f"{model_name}: checkpoint {path!r} holds {type(checkpoint).__name__} without "
            f"tensors, not a state dict; {hint}"
        )
    return checkpoint


def read_state_dict(path: str, model_name: str, url: str, filename: str) -> dict:
    """The state dict in ``path``: ``safetensors`` files by name, anything else with
    ``torch.load(weights_only=True)`` (a Lightning ``state_dict`` is unwrapped)."""
    hint = f"download {filename} from {url}"
    if not Path(path).is_file():
        raise CheckpointError(f"{model_name}: checkpoint {path!r} does not exist; {hint}")
    if str(path).endswith(".safetensors"):
        try:
            return load_file(str(path))
        except Exception as error:  # safetensors raises its own error types
            raise CheckpointError(
                f"{model_name}: checkpoint {path!r}: cannot read it as safetensors "
                f"({type(error).__name__}: {error}); {hint}"
            ) from error
    try:
        checkpoint = read_checkpoint(str(path))
    except CheckpointError as error:
        raise CheckpointError(f"{model_name}: {error}; {hint}") from error
    if isinstance(checkpoint, dict) and isinstance(checkpoint.get("state_dict"), dict):
        checkpoint = checkpoint["state_dict"]
    if not isinstance(checkpoint, dict):
        raise CheckpointError(
            f"{model_name}: checkpoint {path!r} holds a {type(checkpoint).__name__}, "
            f"not a state dict; {hint}"
        )
    return checkpoint


def load_matching(
    module: nn.Module,
    state: dict,
    path: str,
    model_name: str,
    hint: str,
    *,
    ignore: Iterable[str] = (),
) -> None:
    """Load ``state`` into ``module`` after checking that its keys are exactly the
    module's (keys under an ``ignore`` prefix dropped first) with the same shapes;
    otherwise a :class:`CheckpointError` naming ``model_name``, ``path``, the keys at
    fault and ``hint`` (where to get the right file)."""
    prefixes = tuple(ignore)
    state = {
        k: v
        for k, v in state.items()
        if not (isinstance(k, str) and prefixes and k.startswith(prefixes))
    }
    own = module.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(str(k) for k in set(state) - set(own))
    if missing or unexpected:
        raise CheckpointError(
            f"{model_name}: checkpoint {path!r} does not fit: {len(missing)} missing keys "
            f"{missing[:4]}, {len(unexpected)} unexpected keys {unexpected[:4]}; {hint}"
        )
    for key, tensor in state.items():
        if not isinstance(tensor, torch.Tensor) or tuple(tensor.shape) != tuple(own[key].shape):
            shape = (
                tuple(tensor.shape) if isinstance(tensor, torch.Tensor) else type(tensor).__name__
            )
            raise CheckpointError(
                f"{model_name}: checkpoint {path!r} key {key!r} has shape {shape}, expected "
                f"{tuple(own[key].shape)}; {hint}"
            )
    # float32 throughout: a half-precision file must not make the model half precision.
    module.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in state.items()})
