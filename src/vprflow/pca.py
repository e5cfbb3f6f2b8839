"""PCA (optionally whitened) fitted on descriptors and stored as plain arrays.

A fitted PCA is ``mean [D]``, ``components [d, D]`` (rows = principal axes, by
decreasing variance) and ``explained_variance [d]``; projection is
``(x - mean) @ components.T``, divided by ``sqrt(explained_variance)`` when whitening.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vprflow.backbones import l2_normalize


@dataclass(frozen=True)
class Pca:
    mean: np.ndarray  # [D]
    components: np.ndarray  # [d, D]
    explained_variance: np.ndarray  # [d]
    whiten: bool

    def transform(self, x: np.ndarray, normalize: bool = True, eps: float = 1e-12) -> np.ndarray:
        """Project ``x`` ``[N, D]`` -> ``[N, d]`` float32 (L2-normalised by default)."""
        y = (np.asarray(x, dtype=np.float32) - self.mean) @ self.components.T
        if self.whiten:
            y /= np.sqrt(np.maximum(self.explained_variance, eps))
        return l2_normalize(y) if normalize else y


def _sign_fix(components: np.ndarray) -> np.ndarray:
    """Make the largest-magnitude entry of each axis positive (a deterministic sign)."""
    pivots = np.argmax(np.abs(components), axis=1)
    signs = np.sign(components[np.arange(len(components)), pivots])
    return components * np.where(signs == 0, 1, signs)[:, None]


def fit_pca(x: np.ndarray, dim: int, whiten: bool = True, seed: int = 0) -> Pca:
    """Fit PCA to ``x`` ``[N, D]``; ``dim`` is capped at ``min(N - 1, D)``.

    Exact eigen-decomposition of whichever of the covariance ``[D, D]`` or the Gram
    matrix ``[N, N]`` is smaller while that is at most 8192 wide; beyond that, a
    randomised SVD with power iterations (what makes 50,000 x 49,152 feasible).
    Computed in float64 for the small matrices.
    """
    x = np.asarray(x, dtype=np.float32)
    n, d_in = x.shape
    if n < 2:
        raise ValueError(f"PCA needs at least 2 descriptors, got {n}")
    dim = min(dim, n - 1, d_in)
    mean = x.mean(axis=0, dtype=np.float64)
    if min(n, d_in) <= 8192:
        c64 = x.astype(np.float64) - mean
        if d_in <= n:
            values, vectors = np.linalg.eigh(c64.T @ c64)
            top = np.argsort(values)[::-1][:dim]
            components = vectors[:, top].T
            variance = values[top] / (n - 1)
        else:
            values, vectors = np.linalg.eigh(c64 @ c64.T)
            top = np.argsort(values)[::-1][:dim]
            values = np.maximum(values[top], 0.0)
            components = (vectors[:, top].T @ c64) / np.sqrt(np.maximum(values, 1e-300))[:, None]
            variance = values / (n - 1)
    else:
        components, variance = _randomized_pca(x, dim, seed, mean=mean.astype(np.float32))
    return Pca(
        mean=mean.astype(np.float32),
        components=_sign_fix(components).astype(np.float32),
        explained_variance=np.asarray(variance, dtype=np.float32),
        whiten=whiten,
    )


def _randomized_pca(
    x: np.ndarray,
    dim: int,
    seed: int,
    n_iter: int = 4,
    oversample: int = 16,
    mean: np.ndarray | None = None,
):
    """Halko et al. randomised SVD of ``x - mean`` (``[N, D]`` float32).

    The centred matrix is never formed: ``(x - 1 m^T) B = x B - 1 (m^T B)`` and
    ``(x - 1 m^T)^T Q = x^T Q - m (1^T Q)``, so memory stays at one copy of ``x``
    (10 GB for 50,000 SegVLAD descriptors of DINOv2-G).
    """
    n = len(x)
    mean = np.zeros(x.shape[1], dtype=np.float32) if mean is None else mean

    def times(right):  # (x - 1 m^T) @ right
        return x @ right - mean @ right

    def transposed_times(left):  # (x - 1 m^T)^T @ left
        return x.T @ left - np.outer(mean, left.sum(axis=0))

    rng = np.random.default_rng(seed)
    width = min(dim + oversample, min(x.shape))
    basis = times(rng.standard_normal((x.shape[1], width)).astype(np.float32))
    for _ in range(n_iter):
        basis, _ = np.linalg.qr(basis)
        basis, _ = np.linalg.qr(times(transposed_times(basis)))
    basis, _ = np.linalg.qr(basis)
    small = transposed_times(basis).T.astype(np.float64)  # [width, D]
    _, singular, vt = np.linalg.svd(small, full_matrices=False)
    return vt[:dim], singular[:dim] ** 2 / (n - 1)
