"""The vocabulary's spherical k-means: vprflow's (float64 decisions, fixed-order sums; the
same centres on every machine) against faiss's float32 ``Kmeans`` (what the CPU ran
before vocabulary format 4), beside the arithmetic floor.

    python benchmarks/bench_vocabulary.py                  # 50,000 x 1536 -> 32, 100 iterations
    python benchmarks/bench_vocabulary.py --n 200000       # the stage's default max_descriptors
    python benchmarks/bench_vocabulary.py --smoke          # 2,000 x 64 -> 8, seconds

Rows: ``faiss`` (float32, its bundled OpenBLAS), ``vprflow`` on the CPU (numpy
products) and, where ``--device`` (default ``auto``) finds an accelerator, with the
products taken there (torch). Columns:

- ``iters``: iterations run (faiss stops when its objective repeats, vprflow when no
  point moves);
- ``k-means ms``: the k-means alone, fastest of ``--repeats``; ``fit ms``: the stage's
  whole call (``vlad.fit_spherical_kmeans``, the ``mean`` centres);
- ``floor ms``: ``N * K * D * 2 * iters`` flops (the assignment products) over the
  device's matrix-product rate in the precision the row computes in (float32 for
  faiss, float64 for vprflow), measured here on a square product; ``x floor``:
  ``k-means ms`` over it;
- ``max |dc|``: largest difference of a unit centroid's entry from the CPU vprflow row's
  (0 on another device: the same decisions and sums); faiss's may part from it by 1e-3
  and more where a mid-run near tie sends it to a neighbouring solution.

Data: unit points around 64 random directions under 6x as much isotropic noise (a
mixture that k-means takes tens of iterations to settle), seed 0.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))


def make_points(n: int, d: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    directions = rng.standard_normal((64, d)).astype(np.float32)
    x = directions[rng.integers(0, 64, n)] + 6.0 * rng.standard_normal((n, d)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def synchronise(device) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def gemm_rate(device, size: int, dtype) -> float:
    """flops per second of a ``size``-cube product in ``dtype`` on ``device``, best of 3."""
    import torch

    a = torch.randn(size, size, device=device, dtype=dtype)
    b = torch.randn(size, size, device=device, dtype=dtype)
    precision = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision("highest")
    try:
        a @ b
        best = float("inf")
        for _ in range(3):
            synchronise(device)
            start = time.perf_counter()
            a @ b
            synchronise(device)
            best = min(best, time.perf_counter() - start)
    finally:
        torch.set_float32_matmul_precision(precision)
    return 2.0 * size**3 / best


def fastest(function, repeats: int, device=None):
    best, result = float("inf"), None
    for _ in range(repeats):
        if device is not None:
            synchronise(device)
        start = time.perf_counter()
        result = function()
        if device is not None:
            synchronise(device)
        best = min(best, time.perf_counter() - start)
    return best, result


def row(path, device, iterations, seconds, fit, floor, gap) -> None:
    fit = "-" if fit is None else f"{fit * 1e3:.1f}"
    times = f"{seconds * 1e3:.1f} | {fit} | {floor * 1e3:.1f} | {seconds / floor:.2f}"
    print(f"| {path} | {device} | {iterations} | {times} | {gap} |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n", type=int, default=50000, help="points (patch descriptors)")
    parser.add_argument("--dim", type=int, default=1536, help="dimensions (DINOv2-G: 1536)")
    parser.add_argument("--clusters", type=int, default=32)
    parser.add_argument("--iters", type=int, default=100, help="most iterations (n_iter)")
    parser.add_argument("--device", default="auto", help="the accelerator row's device")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--gemm", type=int, default=0, help="rate product size (0: by device)")
    parser.add_argument("--smoke", action="store_true", help="tiny sizes, CPU only")
    args = parser.parse_args()
    if args.smoke:
        args.n, args.dim, args.clusters, args.iters, args.device = 2000, 64, 8, 10, "cpu"

    import faiss
    import torch

    from vprflow.aggregation.kmeans import spherical_kmeans
    from vprflow.aggregation.vlad import fit_spherical_kmeans
    from vprflow.core.devices import resolve_device

    n, d, k, seed = args.n, args.dim, args.clusters, 0
    x = make_points(n, d)
    cpu = torch.device("cpu")
    devices = [cpu]
    accelerator = resolve_device(args.device)
    if accelerator.type != "cpu":
        devices.append(accelerator)
    rates = {}
    for device in devices:
        size = args.gemm or (256 if args.smoke else 2048 if device.type == "cpu" else 8192)
        for dtype in (torch.float32, torch.float64):
            rates[device, dtype] = gemm_rate(device, size, dtype)

    print(
        f"# N = {n:,}, D = {d}, K = {k}, n_iter = {args.iters}; numpy {np.__version__}, "
        f"torch {torch.__version__} ({torch.get_num_threads()} threads), faiss "
        f"{faiss.__version__} ({faiss.omp_get_max_threads()} threads); GEMM rate: "
        + ", ".join(
            f"{device} {str(dtype).removeprefix('torch.')} {rate / 1e9:.0f} GFLOP/s"
            for (device, dtype), rate in rates.items()
        )
    )
    print("| k-means | device | iters | k-means ms | fit ms | floor ms | x floor | max abs dc |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")

    def faiss_run():
        km = faiss.Kmeans(
            d, k, niter=args.iters, spherical=True, seed=seed, max_points_per_centroid=n // k + 1
        )
        km.train(x)
        return km.centroids, len(km.iteration_stats)

    seconds, (centroids, iterations) = fastest(faiss_run, args.repeats)
    fit, (reference, _, runs) = fastest(lambda: spherical_kmeans(x, k, args.iters, seed), 1)
    gap = float(np.abs(centroids.astype(np.float64) - reference).max())
    floor = n * k * d * 2.0 * iterations / rates[cpu, torch.float32]
    row("faiss", "cpu", iterations, seconds, None, floor, f"{gap:.1e}")
    for device in devices:
        where = None if device == cpu else device
        seconds, (centroids, _, runs) = fastest(
            lambda where=where: spherical_kmeans(x, k, args.iters, seed, where),
            args.repeats,
            device,
        )
        fit, _ = fastest(
            lambda device=device: fit_spherical_kmeans(x, k, args.iters, seed, device=str(device)),
            1,
            device,
        )
        floor = n * k * d * 2.0 * runs / rates[device, torch.float64]
        gap = float(np.abs(centroids - reference).max())
        row("vprflow", device, runs, seconds, fit, floor, f"{gap:.1e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
