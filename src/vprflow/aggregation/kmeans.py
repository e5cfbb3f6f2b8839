"""Spherical k-means as faiss trains it (``faiss.Kmeans(spherical=True)``), in torch on
any device (docs/methods.md §3).

faiss 1.15's ``Clustering::train`` with an ``IndexFlatIP``, one run (``nredo = 1``), no
weights and no subsampling (the caller sets ``max_points_per_centroid`` above
``N / K``), step by step:

- initialisation: ``rand_perm(N, seed + 1)``; centroid ``c`` is point ``perm[c]``, then
  L2-normalised. The permutation is drawn by faiss itself, so the start is the same.
- each iteration: every point goes to the centroid of largest inner product (ties broken
  in the order faiss's top-1 search breaks them, :func:`tie_order`); the objective is the
  sum of those products; each centroid becomes the mean of its points (the sum times
  ``1 / count``), an empty one is split off a donor drawn with faiss's generator
  (:func:`split_clusters`), and every centroid is L2-normalised.
- stop after ``n_iter`` iterations, or as soon as the objective, in float32, equals the
  previous iteration's.

What cannot be the same: faiss sums each centroid's points one after another in float32
and takes products through its BLAS; here they are two matrix products per iteration
(assignment, then a one-hot product for the sums) in the input's dtype. The centroids
therefore differ in the last bits, and a point whose two best centroids are that close
may go to the other one (the tests count those). faiss adds the objective's terms one
after another, here in a reduction: when centroids still move but so little that
faiss's float32 objective repeats exactly, one run may stop an iteration before the
other (not seen in the tests and benchmarks).
"""

from __future__ import annotations

from functools import cache

import numpy as np
import torch

# faiss's split perturbation (impl/ClusteringHelpers.cpp): "a bit above machine epsilon
# for float16".
_EPS = np.float32(1.0 / 1024.0)


def initial_indices(n: int, k: int, seed: int) -> np.ndarray:
    """The points faiss takes as its ``k`` initial centroids: the first ``k`` of
    ``rand_perm(n, seed + 1)``, drawn by faiss itself."""
    import faiss

    perm = np.empty(n, dtype=np.int32)
    faiss.rand_perm(faiss.swig_ptr(perm), n, seed + 1)
    return perm[:k].astype(np.int64)


def tie_order(k: int, d: int, n: int) -> tuple[int, ...]:
    """The ``k`` centroid indices in the order faiss's top-1 inner-product search prefers
    them when their products are equal, for ``n`` points of ``d`` dimensions.

    Not always the lowest index: at or above ``n * d = distance_compute_blas_threshold``
    faiss multiplies through BLAS and takes each row's best with a SIMD argmax that keeps
    one best per lane (index mod 8 with AVX2, 16 with AVX-512) before scanning the lanes;
    below it, one product at a time, the lowest index. Read off the installed faiss on
    this machine rather than restated.
    """
    import faiss

    blas = n * d >= faiss.cvar.distance_compute_blas_threshold
    return _read_tie_order(k, blas)


@cache
def _read_tie_order(k: int, blas: bool) -> tuple[int, ...]:
    import faiss

    # One dimension and products of exactly 1 or -1: every remaining centroid ties, the
    # winner is removed each time. Queries outnumber faiss's threads, so the search splits
    # them, not the centroids, as training does.
    queries = np.ones((faiss.omp_get_max_threads() + 1, 1), dtype=np.float32)
    centroids = np.ones((k, 1), dtype=np.float32)
    threshold = faiss.cvar.distance_compute_blas_threshold
    faiss.cvar.distance_compute_blas_threshold = 0 if blas else len(queries) + 1
    try:
        order = []
        for _ in range(k):
            index = faiss.IndexFlatIP(1)
            index.add(centroids)
            _, labels = index.search(queries, 1)
            winner = int(labels[0, 0])
            if centroids[winner, 0] != 1.0 or (labels != winner).any():
                raise RuntimeError(f"faiss's tie order among {k} centroids could not be read")
            order.append(winner)
            centroids[winner, 0] = -1.0
    finally:
        faiss.cvar.distance_compute_blas_threshold = threshold
    return tuple(order)


def split_clusters(counts: np.ndarray, n: int) -> list[tuple[int, int]]:
    """faiss's ``split_clusters``: for each empty cluster ``ci`` in order, the donor
    ``cj`` whose centroid it copies -> ``[(ci, cj), ...]``. ``counts`` float32 ``[K]`` is
    updated in place (each split halves the donor's count, as faiss does)."""
    import faiss

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


def _normalise_rows(c: torch.Tensor) -> torch.Tensor:
    """faiss's ``fvec_renorm_L2``: rows times ``1 / sqrt(|row|^2)``; zero rows stay zero."""
    norm2 = (c * c).sum(dim=1, keepdim=True)
    inverse = torch.where(norm2 > 0, 1.0 / torch.sqrt(norm2), torch.zeros_like(norm2))
    return c * inverse


def _chunk_rows(width: int, device: torch.device) -> int:
    # Rows of a chunk whose blocks are ``width`` wide (the [rows, K] products and one-hot,
    # or a float64 copy of [rows, D]): 16 M elements on a GPU, 1 M on a CPU (near its
    # caches); never fewer than 1,024 rows.
    budget = 1 << 24 if device.type != "cpu" else 1 << 20
    return max(1024, budget // max(width, 1))


def spherical_kmeans(x: torch.Tensor, k: int, n_iter: int, seed: int) -> tuple[torch.Tensor, int]:
    """faiss's spherical k-means of the rows of ``x`` ``[N, D]`` (unit rows, any float
    dtype, any device) -> ``(centroids [K, D], iterations run)``, the centroids unit
    rows in ``x``'s dtype on ``x``'s device."""
    n, d = x.shape
    if n < k:
        raise ValueError(f"k-means needs at least {k} points, got {n}")
    device, dtype = x.device, x.dtype
    if n == k:  # faiss copies the points, unnormalised, and runs no iteration
        return x.clone(), 0
    centroids = _normalise_rows(x[torch.as_tensor(initial_indices(n, k, seed), device=device)])
    order = torch.as_tensor(tie_order(k, d, n), device=device)
    step = _chunk_rows(k, device)
    # faiss's perturbation factors, in faiss's float32 (exact in float64 too).
    plus = torch.tensor([1 + _EPS, 1 - _EPS], dtype=dtype, device=device).repeat(d // 2 + 1)[:d]
    minus = torch.tensor([1 - _EPS, 1 + _EPS], dtype=dtype, device=device).repeat(d // 2 + 1)[:d]
    previous = None
    iterations = 0
    for i in range(n_iter):
        iterations = i + 1
        ranked = centroids[order]
        sums = torch.zeros((k, d), dtype=dtype, device=device)
        counts = torch.zeros(k, dtype=torch.int64, device=device)
        objective = torch.zeros((), dtype=torch.float32, device=device)
        for start in range(0, n, step):
            rows = x[start : start + step]
            products = rows @ ranked.T
            rank = torch.argmax(products, dim=1)  # the first of equal maxima
            best = products.gather(1, rank[:, None])[:, 0]
            labels = order[rank]
            objective += best.to(torch.float32).sum(dtype=torch.float32)
            one_hot = torch.zeros((len(rows), k), dtype=dtype, device=device)
            one_hot[torch.arange(len(rows), device=device), labels] = 1
            sums += one_hot.T @ rows
            counts += torch.bincount(labels, minlength=k)
        host_counts = counts.cpu().numpy().astype(np.float32)
        # faiss multiplies by the float reciprocal of the count (in float32).
        reciprocal = np.divide(
            np.float32(1), host_counts, out=np.zeros_like(host_counts), where=host_counts > 0
        )
        if dtype == torch.float64:
            reciprocal = np.divide(
                1.0, host_counts.astype(np.float64), out=np.zeros(k), where=host_counts > 0
            )
        centroids = sums * torch.as_tensor(reciprocal, dtype=dtype, device=device)[:, None]
        for ci, cj in split_clusters(host_counts, n):
            centroids[ci] = centroids[cj] * plus
            centroids[cj] = centroids[cj] * minus
        centroids = _normalise_rows(centroids)
        value = float(objective)
        if previous is not None and previous != 0 and value == previous:  # faiss: 0 never stops
            break
        previous = value
    return centroids, iterations


def fit_on_device(
    x: np.ndarray, k: int, n_iter: int, seed: int, centres: str, device
) -> np.ndarray:
    """:func:`vprflow.aggregation.vlad.fit_spherical_kmeans` on torch device ``device``
    for unit rows ``x`` ``[N, D]`` float32: the k-means, then the returned centres
    (``unit``, or ``mean``: the float64 means of the points under the unit centres,
    assigned to the first of equal maxima as numpy's ``argmax``) -> ``[K, D]`` float32."""
    from vprflow.core.devices import resolve_device

    device = resolve_device(str(device))
    precision = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision("highest")  # no TF32: float32 products throughout
    try:
        points = torch.from_numpy(x).to(device)
        centroids, _ = spherical_kmeans(points, k, n_iter, seed)
        # vlad's l2_normalize: norms below 1e-12 count as 1e-12.
        unit = centroids / torch.linalg.vector_norm(centroids, dim=1, keepdim=True).clamp_min(1e-12)
        if centres == "unit":
            return unit.cpu().numpy().astype(np.float32)
        d = x.shape[1]
        sums = torch.zeros((k, d), dtype=torch.float64, device=device)
        counts = torch.zeros(k, dtype=torch.int64, device=device)
        step = _chunk_rows(d, device)
        for start in range(0, len(x), step):
            rows = points[start : start + step]
            labels = torch.argmax(rows @ unit.T, dim=1)
            one_hot = torch.zeros((len(rows), k), dtype=torch.float64, device=device)
            one_hot[torch.arange(len(rows), device=device), labels] = 1
            sums += one_hot.T @ rows.to(torch.float64)
            counts += torch.bincount(labels, minlength=k)
        filled = counts > 0
        means = torch.where(
            filled[:, None], sums / counts.clamp_min(1)[:, None].to(torch.float64), unit.double()
        )
        return means.cpu().numpy().astype(np.float32)
    finally:
        torch.set_float32_matmul_precision(precision)
