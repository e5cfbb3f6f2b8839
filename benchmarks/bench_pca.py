"""PCA fit time, peak memory and accuracy at 17places shapes: exact vs randomised.

    python benchmarks/bench_pca.py                      # 20,000 x 49,152 -> 1024 (about 20 min)
    python benchmarks/bench_pca.py --n 3000 --d 6144 --dim 256   # a quick look
    python benchmarks/bench_pca.py --smoke                       # 400 x 512 -> 32

Data: VLAD-like synthetic descriptors in float32, ``latent`` directions with
power-law scales (singular values ~ k^-1/2, so the spectrum decays smoothly through
the 1024th component as SegVLAD's does) plus isotropic noise, written once to a
temporary ``.npy``. Each solver runs in its own process, so its wall time and peak
resident memory (``wait4``'s ``ru_maxrss``, data included) are its own.

Accuracy, per solver:
- ``eig residual``: max over components of ``|C^T C v - s^2 v| / s_1^2`` (``C`` the
  centred data, float64): a certificate that does not need a reference solver;
- ``sine vs exact``: largest principal-angle sine between the solver's and the exact
  solver's subspaces, over all components and over the last 5% of them;
- ``white gram``: max difference of the whitened Gram ``(P W^T)(P W^T)^T`` on 16 probe
  vectors, relative to its largest entry (what whitened retrieval sees).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

BLOCK = 1024


def make_data(path: Path, n: int, d: int, latent: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    directions = (rng.standard_normal((latent, d)) / np.sqrt(d)).astype(np.float32)
    scales = (10.0 * np.arange(1, latent + 1) ** -0.5).astype(np.float32)
    offset = rng.normal(0, 0.1, d).astype(np.float32)
    data = np.lib.format.open_memmap(path, mode="w+", dtype=np.float32, shape=(n, d))
    for start in range(0, n, BLOCK):
        rows = min(BLOCK, n - start)
        factors = rng.standard_normal((rows, latent)).astype(np.float32) * scales
        noise = rng.standard_normal((rows, d)).astype(np.float32) * np.float32(0.01)
        data[start : start + rows] = factors @ directions + noise + offset
    data.flush()
    del data


def fit_one(solver: str, data_path: str, dim: int, out: str) -> None:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
    from vprflow.aggregation.pca import fit_pca

    x = np.load(data_path)
    start = time.perf_counter()
    pca = fit_pca(x, dim, whiten=True, solver=solver)
    seconds = time.perf_counter() - start
    np.savez(
        out,
        mean=pca.mean,
        components=pca.components,
        variance=pca.explained_variance,
        seconds=seconds,
    )


def run_solver(solver: str, data_path: Path, dim: int, folder: Path) -> tuple[dict, float]:
    out = folder / f"{solver}.npz"
    command = [sys.executable, __file__, "--fit", solver, "--data", str(data_path)]
    command += ["--dim", str(dim), "--out", str(out)]
    process = subprocess.Popen(command)
    _, status, usage = os.wait4(process.pid, 0)
    if status != 0:
        raise SystemExit(f"{solver} fit failed (status {status})")
    result = dict(np.load(out))
    return result, usage.ru_maxrss / 1024  # MiB


def eig_residual(data: np.ndarray, fit: dict) -> float:
    """max_i |C^T C v_i - (n-1) var_i v_i| / ((n-1) var_1), C = data - mean, float64."""
    v = fit["components"].astype(np.float64)
    mean = data.mean(axis=0, dtype=np.float64)
    product = np.zeros_like(v)
    for start in range(0, len(data), BLOCK):
        block = np.asarray(data[start : start + BLOCK], dtype=np.float64) - mean
        product += (block @ v.T).T @ block
    n = len(data)
    values = fit["variance"].astype(np.float64) * (n - 1)
    residual = np.linalg.norm(product - values[:, None] * v, axis=1)
    return float(residual.max() / values[0])


def max_sine(components: np.ndarray, reference: np.ndarray) -> float:
    ours = components.astype(np.float64)
    ours /= np.linalg.norm(ours, axis=1, keepdims=True)
    basis = np.linalg.qr(reference.astype(np.float64).T)[0].T
    return float(np.linalg.norm(ours - (ours @ basis.T) @ basis, ord=2))


def whitened_gram(fit: dict, probes: np.ndarray) -> np.ndarray:
    projected = probes @ (fit["components"].astype(np.float64).T / np.sqrt(fit["variance"]))
    return projected @ projected.T


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=20000, help="samples (segment descriptors)")
    parser.add_argument("--d", type=int, default=49152, help="dimension (K x D = 32 x 1536)")
    parser.add_argument("--dim", type=int, default=1024)
    parser.add_argument("--latent", type=int, default=4096)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--solvers", nargs="+", default=["exact", "randomized"])
    parser.add_argument("--fit", help=argparse.SUPPRESS)
    parser.add_argument("--data", help=argparse.SUPPRESS)
    parser.add_argument("--out", help=argparse.SUPPRESS)
    parser.add_argument(
        "--smoke", action="store_true", help="400 x 512 -> 32, 64 latent directions (seconds)"
    )
    args = parser.parse_args()
    if args.smoke:
        args.n, args.d, args.dim, args.latent = 400, 512, 32, 64
    if args.fit:
        fit_one(args.fit, args.data, args.dim, args.out)
        return
    with tempfile.TemporaryDirectory(dir=os.environ.get("TMPDIR")) as folder:
        folder = Path(folder)
        data_path = folder / "data.npy"
        start = time.perf_counter()
        make_data(data_path, args.n, args.d, args.latent, args.seed)
        print(
            f"data {args.n} x {args.d} float32 ({args.n * args.d * 4 / 2**30:.1f} GiB), "
            f"{args.latent} latent directions, made in {time.perf_counter() - start:.0f} s",
            flush=True,
        )
        fits = {}
        for solver in args.solvers:
            fit, peak = run_solver(solver, data_path, args.dim, folder)
            fits[solver] = (fit, peak)
            print(f"{solver}: fitted in {float(fit['seconds']):.1f} s", flush=True)
        data = np.load(data_path, mmap_mode="r")
        probes = np.random.default_rng(1).standard_normal((16, args.d))
        reference = fits.get("exact", (None,))[0]
        tail = max(1, args.dim // 20)
        print()
        print(
            f"| solver | N | D | dim | fit s | peak RSS MiB | eig residual | "
            f"sine vs exact (all) | sine vs exact (last {tail}) | white gram vs exact |"
        )
        print("|---|---|---|---|---|---|---|---|---|---|")
        for solver, (fit, peak) in fits.items():
            residual = eig_residual(data, fit)
            if reference is not None and solver != "exact":
                sine = max_sine(fit["components"], reference["components"])
                sine_tail = max_sine(fit["components"][-tail:], reference["components"])
                exact_gram = whitened_gram(reference, probes)
                gram = np.abs(whitened_gram(fit, probes) - exact_gram).max()
                gram /= np.abs(exact_gram).max()
                compare = f"{sine:.2e} | {sine_tail:.2e} | {gram:.2e}"
            else:
                compare = "- | - | -"
            print(
                f"| {solver} | {args.n} | {args.d} | {len(fit['variance'])} | "
                f"{float(fit['seconds']):.1f} | {peak:.0f} | {residual:.2e} | {compare} |"
            )


if __name__ == "__main__":
    main()
