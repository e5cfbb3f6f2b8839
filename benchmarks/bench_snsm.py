"""Per-image SNSM time: vectorised ``vprflow.aggregation.snsm`` vs a direct per-cell loop.

Three implementations, all starting from the same random token grid and timed end to end
(normalisation, upscaling, windowing, support map):

- ``token``: ``snsm_descriptor`` (token-level shifted products, no window grid built);
- ``grid``: ``support_map(window_grid(...))`` (explicit window vectors, one shifted-array
  product per neighbour offset);
- ``direct``: the plain transcription of the definition, shaped like the published code:
  a Python double loop over support-map cells, one numpy similarity per neighbour.

Usage: python benchmarks/bench_snsm.py [--repeats N] [--direct-repeats N] [--seed S]
       python benchmarks/bench_snsm.py --smoke     # one run of each
"""

from __future__ import annotations

import argparse
import functools
import math
import time

import numpy as np

from vprflow.aggregation.snsm import normalize_tokens, snsm_descriptor, support_map, window_grid

OFFSETS = {
    "diagonal4": [(-1, -1), (-1, 1), (1, -1), (1, 1)],
    "all8": [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if (dr, dc) != (0, 0)],
}

SETTINGS = [
    # (h, w, D, upscale, window, neighbourhood, similarity)
    (28, 28, 768, 4, 2, "diagonal4", "cosine"),  # published default
    (28, 28, 768, 6, 2, "diagonal4", "cosine"),
    (28, 28, 768, 4, 2, "all8", "cosine"),
    (28, 28, 768, 4, 2, "diagonal4", "neg_l2"),
    (28, 28, 768, 4, 4, "diagonal4", "cosine"),
]


def direct_descriptor(tokens, upscale, window, neighbourhood, similarity):
    x = normalize_tokens(tokens, "channel")
    up = np.repeat(np.repeat(x, upscale, axis=0), upscale, axis=1)
    rows, cols = up.shape[0] // window, up.shape[1] // window
    grid = (
        up.reshape(rows, window, cols, window, -1).transpose(0, 2, 1, 3, 4).reshape(rows, cols, -1)
    )
    support = np.zeros((rows, cols), dtype=np.float32)
    for m in range(rows):
        for n in range(cols):
            p = grid[m, n]
            for dr, dc in OFFSETS[neighbourhood]:
                if 0 <= m + dr < rows and 0 <= n + dc < cols:
                    q = grid[m + dr, n + dc]
                    if similarity == "cosine":
                        value = np.dot(p, q) / max(np.linalg.norm(p) * np.linalg.norm(q), 1e-8)
                    else:
                        value = -np.linalg.norm(p - q)
                    support[m, n] += value
    return support.reshape(-1)


def grid_descriptor(tokens, upscale, window, neighbourhood, similarity):
    grid = window_grid(normalize_tokens(tokens, "channel"), upscale, window)
    return support_map(grid, neighbourhood, similarity).reshape(-1)


def best_time(function, repeats):
    times = []
    result = None
    for _ in range(repeats):
        start = time.perf_counter()
        result = function()
        times.append(time.perf_counter() - start)
    return min(times), result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5, help="vectorised runs (best kept)")
    parser.add_argument("--direct-repeats", type=int, default=2, help="direct-loop runs")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--smoke", action="store_true", help="one run of each (about 2 s)")
    args = parser.parse_args()
    if args.smoke:
        args.repeats = args.direct_repeats = 1

    rng = np.random.default_rng(args.seed)
    header = (
        f"{'grid':>10} {'u':>2} {'w':>2} {'neighbours':>10} {'sim':>7} {'length':>6} "
        f"{'token ms':>8} {'grid ms':>8} {'direct ms':>9} {'direct/token':>12} {'max rel diff':>12}"
    )
    print(header)
    print("-" * len(header))
    for h, w, depth, upscale, window, neighbourhood, similarity in SETTINGS:
        tokens = rng.standard_normal((h, w, depth)).astype(np.float32)
        setting = (tokens, upscale, window, neighbourhood, similarity)
        token_s, fast = best_time(functools.partial(snsm_descriptor, *setting), args.repeats)
        grid_s, other = best_time(functools.partial(grid_descriptor, *setting), args.repeats)
        slow_s, slow = best_time(
            functools.partial(direct_descriptor, *setting), args.direct_repeats
        )
        scale = max(float(np.max(np.abs(slow))), 1e-30)
        diff = max(float(np.max(np.abs(fast - slow))), float(np.max(np.abs(other - slow))))
        diff /= scale
        shape = f"{h}x{w}x{depth}"
        print(
            f"{shape:>10} {upscale:>2} {window:>2} {neighbourhood:>10} {similarity:>7} "
            f"{fast.size:>6} {token_s * 1e3:>8.1f} {grid_s * 1e3:>8.1f} {slow_s * 1e3:>9.1f} "
            f"{slow_s / token_s:>11.0f}x {diff:>12.1e}"
        )
        assert math.isfinite(diff)


if __name__ == "__main__":
    main()
