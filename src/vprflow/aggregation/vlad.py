"""VLAD vocabularies and AnyLoc-style VLAD aggregation (docs/methods.md §3-4).

Shapes: ``x`` patch descriptors ``[N, D]``; ``centres`` ``[K, D]``; a VLAD vector is
``[K * D]`` (cluster-major: block ``c`` holds the residual sum of cluster ``c``).
"""

from __future__ import annotations

import numpy as np

from vprflow.aggregation.kmeans import cluster_sums, spherical_kmeans
from vprflow.core.arrays import l2_normalize
from vprflow.core.lazy import lazy_import

torch = lazy_import("torch")
F = lazy_import("torch.nn.functional")

CENTRES = ("mean", "unit")


def fit_spherical_kmeans(
    x: np.ndarray,
    n_clusters: int = 32,
    n_iter: int = 100,
    seed: int = 0,
    centres: str = "mean",
    device: str = "cpu",
) -> np.ndarray:
    """vprflow's spherical (cosine) k-means (:mod:`vprflow.aggregation.kmeans`) ->
    centres ``[K, D]`` float32, the same on every CPU, BLAS kernel and thread count.

    ``x`` is L2-normalised first (in float64, then rounded to float32). No subsampling:
    the caller decides how many descriptors to use. ``device`` (a config device name)
    is where the products are taken; it changes no result.

    ``centres="mean"`` (default, as AnyLoc's cosine k-means): each centre is the plain
    mean of the unit descriptors assigned to it by the k-means' own rule, NOT
    re-normalised, so its norm is below 1 and shrinks with the cluster's spread (the
    published 17places ``c_centers.pt`` has norms 0.36-0.99). VLAD assigns with the
    normalised centres and takes residuals to these un-normalised ones, so the norms
    matter. A cluster that receives no descriptor keeps its unit centroid.
    ``centres="unit"``: the unit-norm centroids.
    """
    if centres not in CENTRES:
        raise ValueError(f"unknown vocabulary centres {centres!r}; expected one of {CENTRES}")
    x = np.asarray(x, dtype=np.float32)
    if len(x) < n_clusters:
        raise ValueError(f"k-means needs at least {n_clusters} descriptors, got {len(x)}")
    if not np.isfinite(x).all():
        raise ValueError("k-means input contains NaN or infinite values")
    unit = l2_normalize(x.astype(np.float64)).astype(np.float32)
    centroids, labels, _ = spherical_kmeans(unit, n_clusters, n_iter, seed, device)
    if centres == "unit":
        return centroids.astype(np.float32)
    counts = np.bincount(labels, minlength=n_clusters)
    means = cluster_sums(unit, labels, n_clusters) / np.maximum(counts, 1)[:, None]
    return np.where(counts[:, None] > 0, means, centroids).astype(np.float32)


def assign(x: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Hard assignment ``argmax_c x . normalize(C_c)`` -> labels ``[N]`` (int64), a numpy
    float32 product through the BLAS kernel of the machine: the assignment VLAD used
    before it followed the authors' torch (:func:`published_labels`), which
    ``benchmarks/check_ties.py`` compares with it."""
    x = np.asarray(x, dtype=np.float32)
    unit = l2_normalize(np.asarray(centres, dtype=np.float32))
    if len(x) == 0:
        return np.zeros(0, dtype=np.int64)
    return np.argmax(x @ unit.T, axis=1).astype(np.int64)


# Which published function assigns the patches of one image to VLAD centres
# (docs/methods.md §4). Both run in torch float32 on the CPU, on every patch of the image
# at once, on the authors' layout.
ASSIGNMENTS = ("anyloc", "segvlad")


def _authors_layout(x: np.ndarray):
    """``x [N, D]`` as the authors hold an image's patches: the ``[N, D]`` view of a
    ``[D, N]`` tensor (``F.normalize(desc [1, D, N], dim=1).permute(0, 2, 1)``). The
    layout, like the product's shape, decides how torch rounds a norm or a product."""
    return torch.from_numpy(np.ascontiguousarray(np.asarray(x, dtype=np.float32).T)).T


def normalize_patches(x: np.ndarray) -> np.ndarray:
    """Each row of ``x [N, D]`` L2-normalised as the published code normalises an image's
    patches: ``torch.nn.functional.normalize(desc [1, D, N], dim=1)`` (eps 1e-12), in
    float32 -> ``[N, D]`` float32. Its rounding differs from a numpy norm (and from torch
    on a ``[N, D]`` layout) in the last bit, enough to move an exact tie."""
    if len(x) == 0:
        return np.asarray(x, dtype=np.float32)
    return F.normalize(_authors_layout(x), dim=1).numpy()


def published_labels(x: np.ndarray, centres: np.ndarray, assignment: str = "anyloc") -> np.ndarray:
    """Hard assignment of one image's patches ``x [N, D]`` to ``centres [K, D]`` as the
    published code computes it -> labels ``[N]`` int64 (docs/methods.md §4):

    - ``anyloc``: AnyLoc's ``VLAD.generate`` -> ``fast_pytorch_kmeans.KMeans.predict``,
      cosine mode: ``normalize(x, dim=-1) @ normalize(C, dim=-1).T``, then
      ``.max(dim=-1)``;
    - ``segvlad``: Revisit-Anything's ``func_vpr.vlad_single``:
      ``argmax(x @ normalize(C, dim=1).T, dim=1)`` (``x`` used as given).

    Both in torch float32 on the CPU, all ``N`` patches in one product, ``x`` in the
    authors' layout (:func:`_authors_layout`), so that an exact float32 tie goes where
    their code sends it on the same CPU (a numpy product rounds otherwise: OpenBLAS's
    kernels differ per CPU; torch's go through MKL). Equal maxima: the first centre.
    """
    if assignment not in ASSIGNMENTS:
        raise ValueError(f"unknown VLAD assignment {assignment!r}; expected one of {ASSIGNMENTS}")
    if len(x) == 0:
        return np.zeros(0, dtype=np.int64)
    patches = _authors_layout(x)
    unit = F.normalize(torch.from_numpy(np.asarray(centres, dtype=np.float32)), dim=-1)
    if assignment == "anyloc":
        return (F.normalize(patches, dim=-1) @ unit.transpose(-2, -1)).max(dim=-1)[1].numpy()
    return torch.argmax(patches @ unit.T, dim=1).numpy()


def vlad_per_region(
    features: np.ndarray,
    regions: np.ndarray,
    centres: np.ndarray,
    labels: np.ndarray | None = None,
    assignment: str = "segvlad",
) -> np.ndarray:
    """VLAD of the patches of every region: ``[S, K * D]`` float32.

    ``features`` ``[N, D]``; ``regions`` bool ``[S, N]`` (for SegVLAD, the patches of
    each segment neighbourhood); ``centres`` ``[K, D]``. Residuals to the
    un-normalised centres, per-cluster sums, intra-normalisation, flatten, L2.
    Patches are sorted by cluster and their centre is subtracted first, so cluster
    ``c``'s residual sums are one product ``regions[:, P_c] @ (x[P_c] - C_c)``:
    ``S * N * D`` multiply-adds in all (the minimum). Labels not given are
    :func:`published_labels` of ``features`` (``assignment``: SegVLAD's by default); the
    sums are numpy's (torch multiplied these small products no faster).
    """
    features = np.asarray(features, dtype=np.float32)
    centres = np.asarray(centres, dtype=np.float32)
    if labels is None:
        labels = published_labels(features, centres, assignment)
    labels = np.asarray(labels)
    k, d = centres.shape
    n_regions = len(regions)
    order = np.argsort(labels, kind="stable")
    bounds = np.searchsorted(labels[order], np.arange(k + 1))
    residuals = features[order] - centres[labels[order]]
    weights = np.asarray(regions)[:, order].astype(np.float32)
    sums = np.zeros((n_regions, k, d), dtype=np.float32)  # the [S, K * D] output layout
    for c in range(k):
        a, b = int(bounds[c]), int(bounds[c + 1])
        if b > a:
            np.matmul(weights[:, a:b], residuals[a:b], out=sums[:, c])
    # Fused normalisation: after intra-normalisation every non-empty block has unit
    # norm, so the final L2 norm is sqrt(#non-empty blocks); one scaling pass does both.
    norms = np.sqrt(np.einsum("skd,skd->sk", sums, sums))
    nonzero = norms > 1e-12
    scale = np.where(nonzero, 1.0 / np.maximum(norms, 1e-12), np.float32(0))
    scale /= np.sqrt(np.maximum(nonzero.sum(axis=1, keepdims=True), 1), dtype=np.float32)
    sums *= scale[:, :, None]
    return sums.reshape(n_regions, k * d)


def vlad(
    x: np.ndarray,
    centres: np.ndarray,
    labels: np.ndarray | None = None,
    assignment: str = "anyloc",
) -> np.ndarray:
    """AnyLoc VLAD of descriptors ``x`` ``[N, D]`` -> ``[K * D]`` float32: the one
    region that holds every patch, assigned as AnyLoc's code does unless ``labels``
    are given."""
    x = np.asarray(x, dtype=np.float32)
    regions = np.ones((1, len(x)), dtype=bool)
    return vlad_per_region(x, regions, centres, labels, assignment)[0]
