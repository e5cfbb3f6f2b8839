"""Global pooling baselines compared with SNSM: GeM, average and max (docs/methods.md §7).

Each function pools ONE image's tokens ``[N, D]`` or ``[h, w, D]`` over all token axes
into ``[D]``. Matching the SNSM authors' baseline code:

- the tokens are expected to be normalised already (the published baselines pool the
  channel-normalised tokens, see :func:`vprflow.aggregation.snsm.normalize_tokens`);
- the pooled vector is NOT L2-normalised by default (the published code hands the raw
  pooled vectors to an exhaustive L2 search); ``l2_normalize=True`` is the usual
  alternative (then each result is divided by ``max(|v|, 1e-12)``);
- GeM keeps signs by default (``negatives="signed"``): the published code computes
  ``m = mean(x**p)`` and returns ``sign(m) * |m|**(1/p)``, with no clamping.
"""

from __future__ import annotations

import math
import numbers

import numpy as np

GEM_NEGATIVES = ("signed", "abs", "clamp")

_NORM_EPS = 1e-12


def _as_tokens(tokens: np.ndarray) -> np.ndarray:
    x = np.asarray(tokens, dtype=np.float64)
    if x.ndim not in (2, 3):
        raise ValueError(f"tokens must be [N, D] or [h, w, D], got shape {x.shape}")
    x = x.reshape(-1, x.shape[-1])
    if x.shape[0] == 0:
        raise ValueError("cannot pool an empty set of tokens")
    return x


def _finish(pooled: np.ndarray, l2_normalize: bool) -> np.ndarray:
    if l2_normalize:
        pooled = pooled / max(float(np.linalg.norm(pooled)), _NORM_EPS)
    return pooled.astype(np.float32)


def gem(
    tokens: np.ndarray,
    p: float = 3.0,
    eps: float = 1e-6,
    negatives: str = "signed",
    l2_normalize: bool = False,
) -> np.ndarray:
    """Generalised-mean pooling ``(mean_i f(x_i))**(1/p)`` per channel.

    Args:
        tokens: ``[N, D]`` or ``[h, w, D]``.
        p: GeM power (> 0); the authors use 3.
        eps: floor used only by ``negatives="clamp"``.
        negatives: how negative activations are handled:
            ``"signed"`` (published default): ``m = mean(sign(x) |x|**p)``, result
            ``sign(m) |m|**(1/p)``. Identical to the published ``mean(x**p)`` for odd integer
            ``p`` (including 3); the published formula would give ``mean(|x|**p)`` for even
            ``p`` and NaN for fractional ``p``, which this sign-preserving form avoids.
            ``"abs"`` (published ``--gem_use_abs``): ``mean(|x|**p)**(1/p)``.
            ``"clamp"`` (Radenovic et al.'s GeM): ``mean(max(x, eps)**p)**(1/p)``.
        l2_normalize: divide the result by its L2 norm (off in the published baseline).

    Returns:
        float32 ``[D]``.
    """
    if negatives not in GEM_NEGATIVES:
        raise ValueError(
            f"unknown GeM negatives mode {negatives!r}; expected one of {', '.join(GEM_NEGATIVES)}"
        )
    if isinstance(p, bool) or not isinstance(p, numbers.Real) or not math.isfinite(p) or p <= 0:
        raise ValueError(f"GeM power p must be a positive number, got {p!r}")
    x = _as_tokens(tokens)
    if negatives == "signed":
        powered = np.sign(x) * np.abs(x) ** p
    elif negatives == "abs":
        powered = np.abs(x) ** p
    else:
        powered = np.maximum(x, eps) ** p
    mean = powered.mean(axis=0)
    return _finish(np.sign(mean) * np.abs(mean) ** (1.0 / p), l2_normalize)


def average_pool(tokens: np.ndarray, l2_normalize: bool = False) -> np.ndarray:
    """Global average pooling of ``[N, D]`` or ``[h, w, D]`` -> float32 ``[D]``."""
    return _finish(_as_tokens(tokens).mean(axis=0), l2_normalize)


def max_pool(tokens: np.ndarray, l2_normalize: bool = False) -> np.ndarray:
    """Global max pooling of ``[N, D]`` or ``[h, w, D]`` -> float32 ``[D]``."""
    return _finish(_as_tokens(tokens).max(axis=0), l2_normalize)


def segment_gem(tokens: np.ndarray, membership: np.ndarray, p: float = 3.0) -> np.ndarray:
    """GeM of each segment's tokens: ``tokens [N, D]`` or ``[h, w, D]``, ``membership``
    bool ``[S, N]`` (which tokens each segment covers) -> float32 ``[S, D]``, each row
    :func:`gem` (``negatives="signed"``) of its segment's tokens, not normalised.

    A segment that covers no token gets a zero row (it then matches nothing better
    than anything else, instead of a NaN that no stage may store).
    """
    x = _as_tokens(tokens)
    member = np.asarray(membership, dtype=bool)
    if member.ndim != 2 or member.shape[1] != x.shape[0]:
        raise ValueError(f"membership must be [S, {x.shape[0]}], got shape {member.shape}")
    if isinstance(p, bool) or not isinstance(p, numbers.Real) or not math.isfinite(p) or p <= 0:
        raise ValueError(f"GeM power p must be a positive number, got {p!r}")
    counts = member.sum(axis=1)
    sums = member.astype(np.float64) @ (np.sign(x) * np.abs(x) ** p)
    mean = sums / np.maximum(counts, 1)[:, None]
    return (np.sign(mean) * np.abs(mean) ** (1.0 / p)).astype(np.float32)
