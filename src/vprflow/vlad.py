"""VLAD vocabularies and AnyLoc-style VLAD aggregation.

Shapes: ``x`` patch descriptors ``[N, D]``; ``centres`` ``[K, D]``; a VLAD vector is
``[K * D]`` (cluster-major: block ``c`` holds the residual sum of cluster ``c``).
"""

from __future__ import annotations

import numpy as np

from vprflow.backbones import l2_normalize


def fit_spherical_kmeans(
    x: np.ndarray, n_clusters: int = 32, n_iter: int = 100, seed: int = 0
) -> np.ndarray:
    """Spherical (cosine) k-means with faiss; returns unit-norm centres ``[K, D]``.

    ``x`` is L2-normalised first. faiss's own subsampling is disabled: the caller
    decides how many descriptors to use.
    """
    import faiss

    x = np.ascontiguousarray(l2_normalize(np.asarray(x, dtype=np.float32)))
    if len(x) < n_clusters:
        raise ValueError(f"k-means needs at least {n_clusters} descriptors, got {len(x)}")
    kmeans = faiss.Kmeans(
        x.shape[1],
        n_clusters,
        niter=n_iter,
        spherical=True,
        seed=seed,
        max_points_per_centroid=max(256, len(x) // n_clusters + 1),
        verbose=False,
    )
    kmeans.train(x)
    return l2_normalize(kmeans.centroids.astype(np.float32))


def assign(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Hard assignment ``argmax_c x . normalize(C_c)`` -> labels ``[N]`` (int64)."""
    import torch

    if len(x) == 0:
        return np.zeros(0, dtype=np.int64)
    scores = torch.from_numpy(np.asarray(x, dtype=np.float32)) @ torch.from_numpy(
        np.ascontiguousarray(l2_normalize(np.asarray(centres, dtype=np.float32)).T)
    )
    return scores.argmax(dim=1).numpy().astype(np.int64)


def normalize_vlad(residual_sums: np.ndarray) -> np.ndarray:
    """Intra-normalise each cluster block, flatten, then L2-normalise.

    ``residual_sums`` ``[..., K, D]`` -> ``[..., K * D]``. Empty clusters stay zero.
    """
    intra = l2_normalize(residual_sums, axis=-1)
    flat = intra.reshape(*intra.shape[:-2], -1)
    return l2_normalize(flat, axis=-1)


def vlad(x: np.ndarray, centres: np.ndarray, labels: np.ndarray | None = None) -> np.ndarray:
    """AnyLoc VLAD of descriptors ``x`` ``[N, D]`` -> ``[K * D]`` float32.

    Residuals are taken to the un-normalised centres, as published.
    """
    x = np.asarray(x, dtype=np.float32)
    centres = np.asarray(centres, dtype=np.float32)
    labels = assign(x, centres) if labels is None else labels
    k = len(centres)
    one_hot = np.zeros((k, len(x)), dtype=np.float32)
    one_hot[labels, np.arange(len(x))] = 1.0
    sums = one_hot @ x
    counts = one_hot.sum(axis=1)
    return normalize_vlad(sums - counts[:, None] * centres)
