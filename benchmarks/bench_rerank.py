"""Re-ranking cost: milliseconds per query to score a query's top K candidates with each
re-ranker (:func:`vprflow.evaluation.rerank.rerank_scores`, what the ``rerank`` stage calls
per query),
at the patch grids of the shipped and published backbones.

    python benchmarks/bench_rerank.py              # K = 100, the cases below, CPU
    python benchmarks/bench_rerank.py --device cuda   # the similarity matrices on a GPU
    python benchmarks/bench_rerank.py --smoke      # tiny grid, K = 5

Inputs are random: each query is a ``[h * w, D]`` grid of unit vectors; half of its
candidates are the same scene shifted by one patch with noise (so they share many
mutual nearest neighbours, as a true match does, and RANSAC has a model to find), the
other half unrelated vectors (a handful of chance mutual pairs). Columns: ``mutual`` is
the mean number of mutual pairs per candidate (what RANSAC fits); ``ms/query`` the
fastest of ``--repeat`` timings of K candidates, ``ms/candidate`` that over K. The
database read is not included: the stage reads the reference features into memory once
(up to 2 GiB), so per query it is an in-memory gather.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))

# (name, grid h, grid w, descriptor dim, patch pixels)
CASES = {
    # DAISY on corridor (the shipped weight-free backbone, 160 x 120): 15 x 20 patches of
    # 104 at 8 px.
    "daisy_corridor": (15, 20, 104, 8),
    # DINOv2 ViT-B/14 at 224 x 224: 16 x 16 patches of 768.
    "dinov2_b_224": (16, 16, 768, 14),
    # DINOv2 ViT-G/14 value facet at 322 x 322 (AnyLoc's 17places-like shape): 23 x 23.
    "dinov2_g_322": (23, 23, 1536, 14),
}
SMOKE = {"smoke": (4, 4, 16, 14)}


def unit(x: np.ndarray) -> np.ndarray:
    return (x / np.linalg.norm(x, axis=-1, keepdims=True)).astype(np.float32)


def inputs(h: int, w: int, dim: int, k: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """``query [h*w, D]`` and ``candidates [k, h*w, D]``: even candidates the query grid
    shifted one patch right with noise, odd ones unrelated."""
    rng = np.random.default_rng(seed)
    scene = unit(rng.standard_normal((h, w + 1, dim)))
    query = scene[:, :w].reshape(h * w, dim)
    shifted = scene[:, 1:].reshape(h * w, dim)
    candidates = np.empty((k, h * w, dim), np.float32)
    for c in range(k):
        if c % 2 == 0:
            candidates[c] = unit(shifted + 0.3 * rng.standard_normal(shifted.shape) / dim**0.5)
        else:
            candidates[c] = unit(rng.standard_normal((h * w, dim)))
    return query, candidates


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--top-k", type=int, default=100, help="candidates per query")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--device", default="cpu", help="cpu, cuda, ... (torch device)")
    parser.add_argument("--cases", default=",".join(CASES), help="comma-separated names")
    parser.add_argument("--smoke", action="store_true", help="tiny grid, K = 5, one repeat")
    args = parser.parse_args()

    import torch

    from vprflow.evaluation.rerank import mutual_nearest_neighbours, rerank_scores

    cases = SMOKE if args.smoke else {n: CASES[n] for n in args.cases.split(",")}
    top_k, repeat = (5, 1) if args.smoke else (args.top_k, args.repeat)
    print(
        f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"torch {torch.__version__} ({torch.get_num_threads()} threads), device "
        f"{args.device}, K = {top_k}, fastest of {repeat}"
    )
    print(f"{'case':16} {'patches':>8} {'dim':>5} {'reranker':>8} {'mutual':>7} "
          f"{'ms/query':>9} {'ms/candidate':>13}")  # fmt: skip
    print("-" * 72)
    for name, (h, w, dim, patch) in cases.items():
        query, candidates = inputs(h, w, dim, top_k, seed=0)
        mutual = np.mean(
            [len(mutual_nearest_neighbours(query, c)[0]) for c in candidates[: min(top_k, 10)]]
        )
        for method in ("mnn", "ransac"):
            rerank_scores(query, candidates[:1], (h, w), patch, method, device=args.device)
            times = []
            for _ in range(repeat):
                started = time.perf_counter()
                rerank_scores(query, candidates, (h, w), patch, method, device=args.device)
                if args.device.startswith("cuda"):
                    torch.cuda.synchronize()
                times.append(time.perf_counter() - started)
            ms = 1000 * min(times)
            print(
                f"{name:16} {h * w:8d} {dim:5d} {method:>8} {mutual:7.1f} "
                f"{ms:9.1f} {ms / top_k:13.3f}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
