"""vprflow's spherical k-means: one result on every CPU, BLAS kernel and thread count
(docs/methods.md §3).

The map vocabulary is vprflow's own step (the authors fit theirs on a GPU with another
library; the published setting uses their published centres), so it is free to be
robust. It follows faiss's ``Kmeans(spherical=True)`` in its start and its handling of
empty clusters, but decides in float64 with a fixed tie order and sums in a fixed order:

- start: ``rand_perm(N, seed + 1)`` drawn by faiss itself; centroid ``c`` is point
  ``perm[c]``, L2-normalised;
- each iteration: every point goes to the centroid of largest inner product, the
  products in float64; centroids whose products come within :data:`TIE` of the best
  tie, and the lowest index among them wins (:func:`nearest`);
- each centroid becomes the float64 mean of its points, summed one point after another
  in index order (:func:`cluster_sums`), an empty one is split off a donor drawn with
  faiss's generator (:func:`split_clusters`) and perturbed by ``1 +- 1/1024``, and every
  centroid is L2-normalised in float64 (a zero row stays zero);
- stop after ``n_iter`` iterations, or as soon as no point changed its cluster.

Why this gives one result: the only step whose rounding depends on the BLAS kernel,
the thread count or the device is the product ``x @ C.T``, and only through its float64
rounding (~1e-16 relative, at most ``D * 2**-53`` for unit rows). A decision can follow
that rounding only where a product lies within it of ``best - TIE``; everything else
(sums, means, norms) is elementwise or numpy's own fixed-order reduction. faiss
decides in float32 through its bundled OpenBLAS, where a point whose two best products
are 1e-7 apart goes one way or the other with the kernel, and from such a point in
mid-run a whole run can end in a neighbouring solution (centres 1e-2 apart).
"""

from __future__ import annotations

import numpy as np

from vprflow.core.arrays import l2_normalize
from vprflow.core.lazy import lazy_import

devices = lazy_import("vprflow.core.devices")
faiss = lazy_import("faiss")
torch = lazy_import("torch")

# Products within this of the best are one tie (far above float64 rounding, ~1e-16 a
# product of unit rows; far below any gap that float32 data can carry, ~1e-7).
TIE = 2.0**-30

# faiss's split perturbation (impl/ClusteringHelpers.cpp): "a bit above machine epsilon
# for float16".
_EPS = 1.0 / 1024.0

# Points per block of the products: a float64 copy of [rows, D] of about 64 MiB.
_BLOCK = 1 << 23


def initial_indices(n: int, k: int, seed: int) -> np.ndarray:
    """The points faiss takes as its ``k`` initial centroids: the first ``k`` of
    ``rand_perm(n, seed + 1)``, drawn by faiss itself."""
    perm = np.empty(n, dtype=np.int32)
    faiss.rand_perm(faiss.swig_ptr(perm), n, seed + 1)
    return perm[:k].astype(np.int64)


def split_clusters(counts: np.ndarray, n: int) -> list[tuple[int, int]]:
    """faiss's ``split_clusters``: for each empty cluster ``ci`` in order, the donor
    ``cj`` whose centroid it copies -> ``[(ci, cj), ...]``. ``counts`` float32 ``[K]`` is
    updated in place (each split halves the donor's count, as faiss does)."""
    k = len(counts)
    if n <= k:
        raise ValueError(f"splitting empty clusters needs more than {k} points, got {n}")
    empty = np.flatnonzero(counts == 0)
    if len(empty) == 0:
        return []
    rng = faiss.RandomGenerator(1234)  # a fresh generator each call, as faiss's
    denominator = np.float64(np.float32(n - k))
    splits = []
    for ci in empty:
        donor = None
        cj = 0
        for _ in range(10 * k):
            # float p = (hassign[cj] - 1.0) / (float)(n - k): double arithmetic, rounded.
            p = np.float32((np.float64(counts[cj]) - 1.0) / denominator)
            if np.float32(rng.rand_float()) < p:
                donor = cj
                break
            cj = (cj + 1) % k
        if donor is None:  # faiss's fallback: the largest cluster (the first of equals)
            donor = int(np.argmax(counts))
        counts[ci] = counts[donor] / np.float32(2)
        counts[donor] -= counts[ci]
        splits.append((int(ci), int(donor)))
    return splits


def nearest(products: np.ndarray) -> np.ndarray:
    """Each row's centroid: the lowest index among those whose product ``[n, K]`` comes
    within :data:`TIE` of the row's best -> ``[n]`` int64."""
    best = products.max(axis=1, keepdims=True)
    return np.argmax(products >= best - TIE, axis=1)


def cluster_sums(x: np.ndarray, labels: np.ndarray, k: int) -> np.ndarray:
    """The float64 sum of the rows of ``x`` ``[N, D]`` per label ``[N]`` -> ``[K, D]``:
    each cluster's rows added one after another in index order (numpy's reduction over
    the first axis adds row after row), so the same on every machine (a BLAS product's
    order is the kernel's)."""
    order = np.argsort(labels, kind="stable")
    counts = np.bincount(labels, minlength=k)
    ends = np.cumsum(counts)
    sums = np.zeros((k, x.shape[1]), dtype=np.float64)
    for c in np.flatnonzero(counts):
        members = order[ends[c] - counts[c] : ends[c]]
        sums[c] = x[members].sum(axis=0, dtype=np.float64)
    return sums


def _block_rows(width: int) -> int:
    return max(1024, _BLOCK // max(width, 1))


class _Products:
    """``x @ C.T`` in float64 for blocks of the rows of ``x`` ``[N, D]``: numpy on the
    CPU, torch on another device (``x`` is copied there once). ``device``: None, a
    config device name, or a torch device (torch there, the CPU included)."""

    def __init__(self, x: np.ndarray, device):
        self.x, self.device = x, None
        if device is None or (isinstance(device, str) and device == "cpu"):
            return
        if not isinstance(device, torch.device):
            device = devices.resolve_device(str(device))
            if device.type == "cpu":
                return
        self.device = device
        self.resident = torch.from_numpy(x).to(device)

    def labels(self, centroids: np.ndarray) -> np.ndarray:
        """:func:`nearest` centroid ``[K, D]`` float64 of every row -> ``[N]`` int64."""
        n, d = self.x.shape
        step = _block_rows(max(d, len(centroids)))
        out = np.empty(n, dtype=np.int64)
        if self.device is None:
            for start in range(0, n, step):
                rows = np.asarray(self.x[start : start + step], dtype=np.float64)
                out[start : start + step] = nearest(rows @ centroids.T)
            return out
        c = torch.from_numpy(centroids).to(self.device)
        for start in range(0, n, step):
            products = self.resident[start : start + step].to(torch.float64) @ c.T
            out[start : start + step] = nearest(products.cpu().numpy())
        return out


def spherical_kmeans(
    x: np.ndarray, k: int, n_iter: int, seed: int, device=None
) -> tuple[np.ndarray, np.ndarray, int]:
    """Spherical k-means of the unit rows of ``x`` ``[N, D]`` (float32 or float64) ->
    ``(centroids [K, D] float64 unit rows, labels [N] int64, iterations run)``, the
    labels each row's :func:`nearest` of the returned centroids. ``device``: where the
    products are taken (a config device name or a torch device; None or ``"cpu"``:
    numpy); the result is the same on any."""
    n, d = x.shape
    if n < k:
        raise ValueError(f"k-means needs at least {k} points, got {n}")
    if n == k:  # faiss copies the points and runs no iteration
        return np.asarray(x, dtype=np.float64).copy(), np.arange(k), 0
    products = _Products(x, device)
    centroids = l2_normalize(np.asarray(x[initial_indices(n, k, seed)], dtype=np.float64))
    plus = np.resize([1 + _EPS, 1 - _EPS], d)
    minus = np.resize([1 - _EPS, 1 + _EPS], d)
    labels = None
    iterations = 0
    for iterations in range(1, n_iter + 1):
        moved = products.labels(centroids)
        if labels is not None and np.array_equal(moved, labels):
            return centroids, labels, iterations
        labels = moved
        counts = np.bincount(labels, minlength=k)
        centroids = cluster_sums(x, labels, k) / np.maximum(counts, 1)[:, None]
        for ci, cj in split_clusters(counts.astype(np.float32), n):
            centroids[ci] = centroids[cj] * plus
            centroids[cj] = centroids[cj] * minus
        centroids = l2_normalize(centroids)
    return centroids, products.labels(centroids), iterations
