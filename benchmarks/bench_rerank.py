"""Re-ranking cost: milliseconds per query to score a query's top K candidates with each
re-ranker, before (one float32 product per candidate) and after batching (one product per
group of candidates, :func:`vprflow.evaluation.rerank.candidate_pairs`), and the matching
alone before and after a given revision, beside the floors of its products, at the patch
grids of the shipped and published backbones.

    python benchmarks/bench_rerank.py              # K = 100, the cases below, CPU
    python benchmarks/bench_rerank.py --device cuda   # the similarity matrices on a GPU
    python benchmarks/bench_rerank.py --smoke      # tiny grid, K = 5

On a machine reached without git, save the old code first and name the copies:
``git show 00ebe21:src/vprflow/evaluation/rerank.py > before_scores.py``, ``git show
023a60e:src/vprflow/evaluation/rerank.py > before_pairs.py``, then ``--before
before_scores.py --before-pairs before_pairs.py``.

Inputs are random: each query is a ``[h * w, D]`` grid of unit vectors; half of its
candidates are the same scene shifted by one patch with noise (so they share many
mutual nearest neighbours, as a true match does, and RANSAC has a model to find), the
other half unrelated vectors (chance mutual pairs). Every timing is the fastest of
``--repeat`` runs, before and after interleaved in each (the machine is shared: the
minimum is the least disturbed run).

Columns: ``mutual`` the mean mutual pairs per candidate (what RANSAC fits); ``before`` the
re-ranker's score function from ``--before`` (default: the last commit with the
per-candidate loop), loaded from ``git show REV:src/vprflow/evaluation/rerank.py`` into a
module here (its ``mnn_scores`` / ``ransac_scores``); ``after`` the stages' path, the
``matches`` stage's ``candidate_pairs`` then the ``rerank`` stage's ``pair_scorer``, checked
equal; ``fp32`` / ``bf16`` the floors: the query's batched products alone (one
``[P, D] x [D, k Q]`` GEMM per group of candidates, as the code groups them) in float32 and
in bf16; ``x bf16`` = after / bf16 floor. For ``ransac``, ``fit`` is the robust fits
alone (``ransac_inliers`` over the stored pairs), with the fit's share of after. ``match``
is the pairs alone (``candidate_pairs``, checked equal to before's), ``match before`` the
same from ``--before-pairs`` (default: the last commit with one product per candidate off
the CPU), ``x fp32`` = match / fp32 floor (the floor being ``K P Q D 2`` flops at the
measured rate of those products). The database read is not included: the stage reads the
reference features into memory once (up to 2 GiB; off the CPU it moves them to the device
once, so ``match`` takes candidates already there, ``match before`` from the host, as each
stage did).
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

# The last commit with one float32 product per candidate.
BEFORE = "00ebe21"
# The last commit with one product per candidate off the CPU (candidate_pairs).
BEFORE_PAIRS = "023a60e"

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


def load_before(rev: str) -> types.ModuleType:
    """``src/vprflow/evaluation/rerank.py`` at ``rev`` as a module of its own; ``rev`` may
    also name a saved copy of that file (for a machine the checkout reaches without git,
    such as a lent GPU: ``git show REV:src/vprflow/evaluation/rerank.py > FILE``)."""
    if Path(rev).is_file():
        source = Path(rev).read_text()
    else:
        source = subprocess.run(
            ["git", "show", f"{rev}:src/vprflow/evaluation/rerank.py"],
            cwd=ROOT, capture_output=True, text=True, check=True,
        ).stdout  # fmt: skip
    # core.registry is gone; the old score functions timed here never called what they
    # imported from it (only its rerank_scores did).
    source = source.replace(
        "from vprflow.core.registry import", "# from vprflow.core.registry import"
    )
    name = f"rerank_before_{len([m for m in sys.modules if m.startswith('rerank_before')])}"
    module = types.ModuleType(name)
    sys.modules[name] = module  # where dataclasses look up a class's module
    exec(compile(source, f"{rev}:rerank.py", "exec"), module.__dict__)
    return module


def fastest(repeat: int, calls: dict, sync) -> dict:
    """``{name: fastest seconds}`` of each call, the calls interleaved in every repeat."""
    best = dict.fromkeys(calls, float("inf"))
    for call in calls.values():  # warm-up: first-call kernel set-up is not re-ranking
        call()
    for _ in range(repeat):
        for name, call in calls.items():
            started = time.perf_counter()
            call()
            sync()
            best[name] = min(best[name], time.perf_counter() - started)
    return best


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--top-k", type=int, default=100, help="candidates per query")
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--device", default="cpu", help="cpu, cuda, ... (torch device)")
    parser.add_argument("--cases", default=",".join(CASES), help="comma-separated names")
    parser.add_argument("--before", default=BEFORE, help="old code: git revision or rerank.py")
    parser.add_argument(
        "--before-pairs", default=BEFORE_PAIRS, help="old matching: git revision or rerank.py"
    )
    parser.add_argument("--smoke", action="store_true", help="tiny grid, K = 5, one repeat")
    args = parser.parse_args()

    import torch

    from vprflow.evaluation import rerank as after
    from vprflow.evaluation.rerank import reranker

    before = load_before(args.before)
    before_pairs = load_before(args.before_pairs).candidate_pairs
    cases = SMOKE if args.smoke else {n: CASES[n] for n in args.cases.split(",")}
    top_k, repeat = (5, 1) if args.smoke else (args.top_k, args.repeat)
    device = torch.device(args.device)

    def sync() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize()

    print(
        f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
        f"torch {torch.__version__} ({torch.get_num_threads()} threads), device "
        f"{args.device}, K = {top_k}, fastest of {repeat}, before = {args.before}, "
        f"match before = {args.before_pairs}; times in ms per query"
    )
    print(
        "| case | patches | dim | reranker | mutual | before | after | speed-up | fp32 | "
        "bf16 | x bf16 | fit (share) | match before | match | x fp32 |"
    )
    print("|---|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    failed = False
    for name, (h, w, dim, patch) in cases.items():
        query_np, candidates_np = inputs(h, w, dim, top_k, seed=0)
        query = torch.from_numpy(query_np).to(device)
        candidates = torch.from_numpy(candidates_np)
        centres = after.patch_centres(h, w, patch)
        n = h * w
        group = max(1, after._product_elements(device) // (n * n))
        on_device = candidates.to(device)
        pairs = after.candidate_pairs(query, on_device)
        mutual = np.mean([len(i) for i, _, _ in pairs])
        if not all(
            all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
            for a, b in zip(pairs, before_pairs(query, candidates), strict=True)
        ):
            print(f"# {name}: pairs differ from match before's", file=sys.stderr)
            failed = True

        def floor(dtype, on_device=on_device, query=query, group=group):
            q = query.to(dtype)
            flat = on_device.to(dtype).reshape(-1, on_device.shape[2])
            step = group * on_device.shape[1]
            sync()
            started = time.perf_counter()
            for start in range(0, flat.shape[0], step):
                q @ flat[start : start + step].T
            sync()
            return time.perf_counter() - started

        for method in ("mnn", "ransac"):
            settings = reranker(method).settings({})
            old_fn = getattr(before, f"{method}_scores")
            score = after.pair_scorer(method, {}, (h, w), patch)

            def old(fn=old_fn, settings=settings, q=query, c=candidates, xy=centres, patch=patch):
                return fn(q, c, xy, patch, **settings)

            def new(score=score, q=query, c=on_device):
                return score(after.candidate_pairs(q, c))

            if not np.array_equal(old(), new()):
                print(f"# {name} {method}: scores differ from before", file=sys.stderr)
                failed = True
            fit_pairs = [(centres[i], centres[j]) for i, j, _ in pairs]
            pixels = settings.get("threshold", 1.0) * patch
            fit_options = {k: settings[k] for k in ("seed", "model", "max_iters", "confidence")
                           if k in settings}  # fmt: skip

            calls = {"before": old, "after": new}
            if method == "ransac":
                calls["match before"] = lambda q=query, c=candidates: before_pairs(q, c)
                calls["match"] = lambda q=query, c=on_device: after.candidate_pairs(q, c)
                calls["fit"] = lambda fit_pairs=fit_pairs, pixels=pixels, o=fit_options: [
                    after.ransac_inliers(a, b, pixels, **o) for a, b in fit_pairs
                ]
            ms = {k: 1000 * v for k, v in fastest(repeat, calls, sync).items()}
            floor(torch.float32), floor(torch.bfloat16)  # warm-up
            ms["fp32"] = 1000 * min(floor(torch.float32) for _ in range(repeat))
            ms["bf16"] = 1000 * min(floor(torch.bfloat16) for _ in range(repeat))
            if "match" in ms:
                match = (
                    f"{ms['match before']:.1f} | {ms['match']:.1f} | {ms['match'] / ms['fp32']:.2f}"
                )
            else:
                match = "- | - | -"
            fit = f"{ms['fit']:.1f} ({100 * ms['fit'] / ms['after']:.0f}%)" if "fit" in ms else "-"
            print(
                f"| {name} | {n} | {dim} | {method} | {mutual:.1f} | {ms['before']:.1f} | "
                f"{ms['after']:.1f} | {ms['before'] / ms['after']:.1f}x | {ms['fp32']:.1f} | "
                f"{ms['bf16']:.1f} | {ms['after'] / ms['bf16']:.2f} | {fit} | {match} |"
            )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
