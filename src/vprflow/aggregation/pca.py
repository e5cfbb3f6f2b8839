"""PCA (optionally whitened) fitted on descriptors, as plain arrays (docs/methods.md §5).

A fitted PCA is ``mean [D]``, ``components [d, D]`` (rows = principal axes, by
decreasing variance) and ``explained_variance [d]``; projection is
``(x - mean) @ components.T``, divided by ``sqrt(explained_variance)`` when whitening.

``solver="exact"`` (default; the published SegVLAD code fits scikit-learn's PCA with
an exact ARPACK solver) eigen-decomposes whichever of the covariance ``[D, D]`` or the
Gram matrix ``[N, N]`` of the centred data is smaller, accumulated in float64, at any
size. ``solver="randomized"`` is Halko et al.'s randomised SVD (4 power iterations,
oversampling 16): much cheaper at 17places shapes, but its trailing components are
inexact (principal-angle errors of several percent in the last few percent of 1024
components), which whitening then weights as much as the leading ones.

Both cap the number of components at the numerical rank of the centred sample: a
direction with no variance would otherwise be whitened by ``1 / sqrt(~0)``.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass

import numpy as np

from vprflow.core.arrays import l2_normalize
from vprflow.core.lazy import lazy_import

linalg = lazy_import("scipy.linalg")

log = logging.getLogger("vprflow")

SOLVERS = ("exact", "randomized")

# Rows or columns of the float32 input converted to float64 at a time.
_BLOCK = 2048


@dataclass(frozen=True)
class Pca:
    mean: np.ndarray  # [D]
    components: np.ndarray  # [d, D]
    explained_variance: np.ndarray  # [d]
    whiten: bool

    @property
    def dim(self) -> int:
        """Number of components (may be below the dimension asked for: rank cap)."""
        return len(self.components)

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


def fit_pca(
    x: np.ndarray, dim: int, whiten: bool = True, seed: int = 0, solver: str = "exact"
) -> Pca:
    """Fit PCA to ``x`` ``[N, D]`` with at most ``dim`` components.

    ``dim`` is capped at ``min(N - 1, D)`` and at the numerical rank of the centred
    data: eigenvalues below ``max(N, D) * eps * largest`` are numerically zero (``eps``
    of float64 for the exact solver, whose eigenvalues carry that relative error; for
    the float32 randomised solver the same rule on singular values with float32's
    ``eps``, as ``numpy.linalg.matrix_rank``). A capped fit logs a warning. ``seed``
    only matters to the randomised solver.
    """
    if solver not in SOLVERS:
        raise ValueError(f"unknown PCA solver {solver!r}; expected one of {SOLVERS}")
    x = np.asarray(x, dtype=np.float32)
    n, d_in = x.shape
    if n < 2:
        raise ValueError(f"PCA needs at least 2 descriptors, got {n}")
    asked = dim
    dim = min(dim, n - 1, d_in)
    mean = x.mean(axis=0, dtype=np.float64)
    if solver == "exact":
        components, variance = _exact_pca(x, mean, dim)
        rank_tol = max(n, d_in) * np.finfo(np.float64).eps
    else:
        components, variance = _randomized_pca(x, dim, seed, mean=mean.astype(np.float32))
        rank_tol = (max(n, d_in) * np.finfo(np.float32).eps) ** 2
    keep = variance > rank_tol * max(float(variance[0]) if len(variance) else 0.0, 0.0)
    if not keep.all():
        components, variance = components[keep], variance[keep]
    if len(variance) < asked:
        log.warning(
            "PCA dim capped at %d (asked %d): %d samples of dimension %d have numerical rank %d",
            len(variance),
            asked,
            n,
            d_in,
            len(variance),
        )
    if len(variance) == 0:
        raise ValueError(f"PCA: the {n} samples are all identical; nothing to fit")
    return Pca(
        mean=mean.astype(np.float32),
        components=_sign_fix(components).astype(np.float32),
        explained_variance=np.asarray(variance, dtype=np.float32),
        whiten=whiten,
    )


def exact_pca_bytes(n: int, d: int, dim: int) -> int:
    """Peak bytes the exact solver allocates beyond ``x`` itself: the float64
    ``min(N, D)^2`` matrix, one float64 block, the eigenvectors and components."""
    m = min(n, d)
    return 8 * (m * m + _BLOCK * max(n, d) + m * dim + dim * d)


def _available_bytes() -> int | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError):
        return None


def _exact_pca(x: np.ndarray, mean: np.ndarray, dim: int) -> tuple[np.ndarray, np.ndarray]:
    """Top ``dim`` principal axes ``[dim, D]`` (float64) and variances ``[dim]``.

    The smaller of ``C^T C`` and ``C C^T`` (``C = x - mean``) is summed in float64 from
    float32 blocks (never a float64 copy of ``x``), then only its top ``dim``
    eigenpairs are computed (LAPACK ``syevr``).
    """
    n, d = x.shape
    need, free = exact_pca_bytes(n, d, dim), _available_bytes()
    if free is not None and need > free:
        raise MemoryError(
            f"exact PCA of {n} samples x {d} dimensions needs about {need / 2**30:.1f} GiB "
            f"beyond the samples, but {free / 2**30:.1f} GiB are available: lower "
            "pca.max_samples, or set pca.solver: randomized"
        )
    m = min(n, d)
    matrix = np.zeros((m, m), dtype=np.float64)
    if d <= n:  # covariance: sum of C_rows^T C_rows
        for start in range(0, n, _BLOCK):
            block = x[start : start + _BLOCK].astype(np.float64) - mean
            matrix += block.T @ block
    else:  # Gram: sum over column blocks of C_cols C_cols^T
        for start in range(0, d, _BLOCK):
            block = x[:, start : start + _BLOCK].astype(np.float64) - mean[start : start + _BLOCK]
            matrix += block @ block.T
    values, vectors = linalg.eigh(
        matrix, subset_by_index=[m - dim, m - 1], driver="evr", overwrite_a=True
    )
    del matrix
    values, vectors = np.maximum(values[::-1], 0.0), vectors[:, ::-1]
    if d <= n:
        return np.ascontiguousarray(vectors.T), values / (n - 1)
    # Gram side: axis_i = C^T u_i / sqrt(lambda_i); rank-deficient axes are dropped by
    # the caller, so divide only where lambda is not (numerically) zero.
    scale = np.where(values > 0, 1.0 / np.sqrt(np.where(values > 0, values, 1.0)), 0.0)
    components = np.empty((dim, d), dtype=np.float64)
    for start in range(0, d, _BLOCK):
        block = x[:, start : start + _BLOCK].astype(np.float64) - mean[start : start + _BLOCK]
        components[:, start : start + _BLOCK] = (vectors.T @ block) * scale[:, None]
    return components, values / (n - 1)


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
