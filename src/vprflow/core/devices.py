"""Choosing the torch device and floating-point precision for model inference.

Config values are plain strings so they can sit in YAML and in cache keys:

- device: ``"auto"`` (CUDA, else Apple MPS, else CPU), ``"cpu"``, ``"cuda"``,
  ``"cuda:<index>"`` or ``"mps"``.
- dtype: ``"float32"``, ``"bfloat16"`` or ``"float16"``.

float16 on the CPU is refused rather than silently replaced by another precision: the
dtype is part of the workflow's cache key, so a quiet fallback would store float32
features under a float16 key. bfloat16 is the reduced precision that runs on CPUs.
"""

from __future__ import annotations

import math

import torch

from vprflow.core.dtypes import COMPUTE_DTYPES

DTYPES = {name: getattr(torch, name) for name in COMPUTE_DTYPES}


def _mps_available() -> bool:
    backend = getattr(torch.backends, "mps", None)
    return bool(backend is not None and backend.is_available())


def resolve_device(name: str) -> torch.device:
    """Turn a config device string into a :class:`torch.device`.

    ``"auto"`` picks CUDA when available, then MPS, then CPU. Asking for ``"cuda"``
    (or ``"mps"``) on a machine without it raises ``RuntimeError`` instead of
    falling back, so a GPU job never runs on the CPU unnoticed.
    """
    text = str(name).strip().lower()
    if text == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda")
        if _mps_available():
            return torch.device("mps")
        return torch.device("cpu")
    if text == "cpu":
        return torch.device("cpu")
    if text == "cuda" or text.startswith("cuda:"):
        if not torch.cuda.is_available():
            raise RuntimeError(
                f"device {name!r} requested but CUDA is not available in this torch build "
                f"(torch {torch.__version__}); use device 'cpu' or 'auto', or install a "
                "CUDA-enabled torch"
            )
        device = torch.device(text)
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise RuntimeError(
                f"device {name!r} requested but only {torch.cuda.device_count()} CUDA "
                "device(s) are visible"
            )
        return device
    if text == "mps":
        if not _mps_available():
            raise RuntimeError(f"device {name!r} requested but Apple MPS is not available")
        return torch.device("mps")
    raise ValueError(f"unknown device {name!r}; expected 'auto', 'cpu', 'cuda', 'cuda:N' or 'mps'")


def resolve_dtype(name: str, device: torch.device | str) -> torch.dtype:
    """Turn a config dtype string into a :class:`torch.dtype` usable on ``device``.

    Raises ``ValueError`` for unknown names and for ``"float16"`` on the CPU (see the
    module docstring for why this is an error, not a fallback).
    """
    text = str(name).strip().lower()
    if text not in DTYPES:
        raise ValueError(f"unknown dtype {name!r}; expected one of {sorted(DTYPES)}")
    device_type = torch.device(device).type
    if text == "float16" and device_type == "cpu":
        raise ValueError(
            "dtype 'float16' is not supported on the CPU (slow, and not silently replaced "
            "because the dtype is part of the cache key); use 'bfloat16' or 'float32' on "
            "the CPU, or run on a GPU"
        )
    return DTYPES[text]


# ``batch_size: auto`` on a GPU: the largest batch whose activations fit this share of
# the memory free once the model is loaded (the rest absorbs fragmentation and the
# allocator's rounding), and never more than MAX_AUTO_BATCH images: past a few thousand
# tokens a batch the GPU is busy already, and larger batches only hold more host memory
# (the images read ahead and the features waiting to be written).
AUTO_BATCH_MEMORY_SHARE = 0.8
MAX_AUTO_BATCH = 64


def free_memory(device: torch.device) -> int:
    """Bytes a CUDA ``device`` can still give this process: what the driver reports
    free plus what torch's caching allocator holds but does not use."""
    free, _ = torch.cuda.mem_get_info(device)
    return int(free + torch.cuda.memory_reserved(device) - torch.cuda.memory_allocated(device))


def batch_for_memory(free_bytes: int, bytes_per_image: int, cap: int = MAX_AUTO_BATCH) -> int:
    """Images a batch whose activations take ``bytes_per_image`` each can hold within
    :data:`AUTO_BATCH_MEMORY_SHARE` of ``free_bytes``: at least 1, at most ``cap``."""
    if bytes_per_image <= 0:
        return max(1, cap)
    fits = math.floor(AUTO_BATCH_MEMORY_SHARE * free_bytes / bytes_per_image)
    return max(1, min(cap, fits))
