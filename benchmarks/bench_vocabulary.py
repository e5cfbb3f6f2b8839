"""The vocabulary's spherical k-means: faiss on the CPU against the torch k-means on each
device, beside the arithmetic floor.

    python benchmarks/bench_vocabulary.py                  # 50,000 x 1536 -> 32, 100 iterations
    python benchmarks/bench_vocabulary.py --n 200000       # the stage's default max_descriptors
    python benchmarks/bench_vocabulary.py --smoke          # 2,000 x 64 -> 8, seconds

Rows: ``faiss`` (what the stage runs on the CPU), ``before``: the stage's call as it was
at ``--before`` (``src/vprflow/aggregation/vlad.py`` from ``git show``; default
``0223a6d``, before the k-means ran on the stage's device; its ``fit ms`` only), then
``torch`` on the CPU and, where ``--device`` (default ``auto``) finds an accelerator,
on it (what the stage runs there).
Columns:

- ``iters``: iterations run (both stop when the objective stops changing);
- ``k-means ms``: the k-means alone (``vlad.spherical_centroids`` for faiss,
  ``kmeans.spherical_kmeans`` for torch), fastest of ``--repeats``;
- ``fit ms``: the stage's whole call with the ``mean`` centres (one more assignment and
  the float64 means): ``vlad.fit_spherical_kmeans`` for faiss, and what it calls off
  the CPU, ``kmeans.fit_on_device``, for torch (on the CPU too);
- ``floor ms``: ``N * K * D * 2 * iters`` flops (the assignment products) over the
  device's float32 matrix-product rate, measured here on a square product
  (``--gemm``); ``x floor``: ``k-means ms`` over it. The torch k-means does a second
  product of that size per iteration (the one-hot sums), so 2x is its arithmetic;
- ``max |dc|``: largest difference of a unit centroid's entry from faiss's;
  ``differ``: final assignments (argmax under the centroids) unlike faiss's, and
  ``near ties``: points whose two best products under faiss's centroids are within
  1e-5. A large ``max |dc|`` (1e-3 and more) with other ``iters`` means the runs
  parted: float32 k-means follows one course until a point's two best products come
  within rounding (~1e-6) of each other, and either may win there; faiss itself parts
  so from its own run when its SIMD level changes (AVX2 against none: 1 of 10 runs of
  20,000 x 384 -> 32 on the CPU). A row then says ``parted``; it is not an error.

Data: unit points around 64 random directions under 6x as much isotropic noise (a
mixture that k-means takes tens of iterations to settle), seed 0.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "src"))

NEAR_TIE = 1e-5
# The commit whose vocabulary k-means was faiss's on every device.
BEFORE = "0223a6d"


def load_before(rev: str) -> types.ModuleType:
    """``src/vprflow/aggregation/vlad.py`` at ``rev`` as a module of its own."""
    path = "src/vprflow/aggregation/vlad.py"
    source = subprocess.run(
        ["git", "show", f"{rev}:{path}"], cwd=REPO, capture_output=True, text=True, check=True
    ).stdout
    module = types.ModuleType("vlad_before")
    exec(compile(source, f"{rev}:{path}", "exec"), module.__dict__)
    return module


def make_points(n: int, d: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    directions = rng.standard_normal((64, d)).astype(np.float32)
    x = directions[rng.integers(0, 64, n)] + 6.0 * rng.standard_normal((n, d)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def synchronise(device) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def gemm_rate(device, size: int) -> float:
    """float32 flops per second of a ``size``-cube product on ``device``, best of 3."""
    import torch

    a = torch.randn(size, size, device=device)
    b = torch.randn(size, size, device=device)
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


def row(path, device, iterations, seconds, fit, floor, gap, differ, near) -> None:
    times = f"{seconds * 1e3:.1f} | {fit * 1e3:.1f} | {floor * 1e3:.1f} | {seconds / floor:.2f}"
    print(f"| {path} | {device} | {iterations} | {times} | {gap} | {differ} | {near} |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--n", type=int, default=50000, help="points (patch descriptors)")
    parser.add_argument("--dim", type=int, default=1536, help="dimensions (DINOv2-G: 1536)")
    parser.add_argument("--clusters", type=int, default=32)
    parser.add_argument("--iters", type=int, default=100, help="most iterations (n_iter)")
    parser.add_argument("--device", default="auto", help="the accelerator row's device")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--gemm", type=int, default=0, help="rate product size (0: by device)")
    parser.add_argument("--before", default=BEFORE, help="the commit of the 'before' row")
    parser.add_argument("--smoke", action="store_true", help="tiny sizes, CPU only")
    args = parser.parse_args()
    if args.smoke:
        args.n, args.dim, args.clusters, args.iters, args.device = 2000, 64, 8, 10, "cpu"

    import faiss
    import torch

    from vprflow.aggregation.kmeans import fit_on_device, spherical_kmeans
    from vprflow.aggregation.vlad import fit_spherical_kmeans, l2_normalize, spherical_centroids
    from vprflow.core.devices import resolve_device

    n, d, k, seed = args.n, args.dim, args.clusters, 0
    x = make_points(n, d)
    unit = np.ascontiguousarray(l2_normalize(x))  # as fit_spherical_kmeans normalises
    devices = [torch.device("cpu")]
    accelerator = resolve_device(args.device)
    if accelerator.type != "cpu":
        devices.append(accelerator)
    rates = {}
    for device in devices:
        size = args.gemm or (256 if args.smoke else 2048 if device.type == "cpu" else 8192)
        rates[device] = gemm_rate(device, size)

    print(
        f"# N = {n:,}, D = {d}, K = {k}, n_iter = {args.iters}; torch {torch.__version__} "
        f"({torch.get_num_threads()} threads), faiss {faiss.__version__} "
        f"({faiss.omp_get_max_threads()} threads); float32 GEMM rate: "
        + ", ".join(f"{device} {rate / 1e9:.0f} GFLOP/s" for device, rate in rates.items())
    )
    header = (
        "| path | device | iters | k-means ms | fit ms | floor ms | x floor "
        "| max abs dc | differ | near ties |"
    )
    print(header)
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")

    cpu = torch.device("cpu")
    seconds, (reference, iterations) = fastest(
        lambda: spherical_centroids(x, k, args.iters, seed), args.repeats
    )
    before = load_before(args.before)
    # Interleaved, so that a load change on a shared machine hits both alike.
    fit = previous = float("inf")
    for _ in range(args.repeats):
        previous = min(
            previous, fastest(lambda: before.fit_spherical_kmeans(x, k, args.iters), 1)[0]
        )
        fit = min(fit, fastest(lambda: fit_spherical_kmeans(x, k, args.iters, device="cpu"), 1)[0])
    floor = n * k * d * 2.0 * iterations / rates[cpu]
    products = x.astype(np.float64) @ reference.T.astype(np.float64)
    ranked = np.sort(products, axis=1)
    near = ranked[:, -1] - ranked[:, -2] < NEAR_TIE
    labels = np.argmax(products, axis=1)
    row("faiss", "cpu", iterations, seconds, fit, floor, "-", "-", int(near.sum()))
    print(f"| before ({args.before}) | cpu | - | - | {previous * 1e3:.1f} | - | - | - | - | - |")
    parted = []
    for device in devices:
        points = torch.from_numpy(x).to(device)

        def run(points=points):
            precision = torch.get_float32_matmul_precision()
            torch.set_float32_matmul_precision("highest")  # as fit_on_device runs it
            try:
                return spherical_kmeans(points, k, args.iters, seed)
            finally:
                torch.set_float32_matmul_precision(precision)

        seconds, (centroids, runs) = fastest(run, args.repeats, device)
        # What fit_spherical_kmeans runs off the CPU (on the CPU it runs faiss instead).
        fit, _ = fastest(
            lambda device=device: fit_on_device(unit, k, args.iters, seed, "mean", str(device)),
            1,
            device,
        )
        centroids = centroids.cpu().numpy().astype(np.float32)
        floor = n * k * d * 2.0 * runs / rates[device]
        gap = float(np.abs(centroids.astype(np.float64) - reference).max())
        differ = int((np.argmax(x @ centroids.T, axis=1) != labels).sum())
        row("torch", device, runs, seconds, fit, floor, f"{gap:.1e}", differ, int(near.sum()))
        if runs != iterations or gap > 1e-4:
            parted.append(str(device))
    for device in parted:
        print(f"parted: torch on {device} ended in another k-means solution than faiss's")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
