"""Per-image time of each numeric stage, on corridor-sized and DINOv2-G-shaped inputs.

    python benchmarks/bench_stages.py [--repeats 20]
    python benchmarks/bench_stages.py --smoke   # corridor shapes only, small search

Shapes: "corridor" = what the shipped config gives on corridor (daisy, 160 x 120,
8-pixel patches: 15 x 20 patches x 104 channels, ~40 SLIC segments at 80 x 60);
"dinov2-g" = the published SegVLAD setting (34 x 45 patches x 1536 channels of a
640 x 480 image, 85 SAM-like overlapping masks at 320 x 240, K = 32, order 3).
Also checks that the fast SegVLAD equals a plain float64 per-segment loop.
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np

from vprflow.aggregation.pca import fit_pca
from vprflow.aggregation.segvlad import (
    mask_patch_membership,
    neighbourhood,
    segment_adjacency,
    segment_centroids,
)
from vprflow.aggregation.vlad import assign, vlad, vlad_per_region
from vprflow.core.arrays import l2_normalize
from vprflow.models.backbones import DaisyBackbone
from vprflow.models.segmenters import SlicSegmenter
from vprflow.search.flat import flat_knn
from vprflow.search.voting import vote_ranking


def best_of(function, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return min(times) * 1000


def random_masks(rng, count: int, height: int, width: int) -> np.ndarray:
    """Overlapping blob masks, like SAM's (sizes from tiny to a quarter of the image)."""
    yy, xx = np.mgrid[0:height, 0:width]
    masks = np.zeros((count, height, width), dtype=bool)
    for s in range(count):
        cy, cx = rng.uniform(0, height), rng.uniform(0, width)
        ry, rx = rng.uniform(3, height / 4), rng.uniform(3, width / 4)
        masks[s] = ((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 < 1
    return masks


def direct_segvlad(features, regions, centres) -> np.ndarray:
    """Plain per-segment, per-cluster float64 loop (the formula, not the fast path)."""
    x = features.astype(np.float64)
    c = centres.astype(np.float64)
    labels = np.argmax(x @ (c / np.linalg.norm(c, axis=1, keepdims=True)).T, axis=1)
    out = np.zeros((len(regions), c.size))
    for s, region in enumerate(regions):
        blocks = np.zeros_like(c)
        for k in range(len(c)):
            members = region & (labels == k)
            if members.any():
                blocks[k] = (x[members] - c[k]).sum(axis=0)
        norms = np.linalg.norm(blocks, axis=1, keepdims=True)
        blocks = np.where(norms > 0, blocks / np.maximum(norms, 1e-300), 0)
        flat = blocks.ravel()
        out[s] = flat / max(np.linalg.norm(flat), 1e-300)
    return out


def bench(name, grid, dim, n_segments, mask_size, patch, repeats, rng, daisy_image=None):
    h, w = grid
    features = l2_normalize(rng.standard_normal((h * w, dim)).astype(np.float32))
    centres = l2_normalize(rng.standard_normal((32, dim)).astype(np.float32))
    masks = random_masks(rng, n_segments, *mask_size)
    image_size = (h * patch + patch // 2, w * patch + patch // 2)
    rows = []
    if daisy_image is not None:
        daisy = DaisyBackbone(patch_size=patch)
        rows.append(
            ("features (daisy)", best_of(lambda: daisy.features(daisy_image[None]), repeats))
        )
        slic = SlicSegmenter(n_segments=40)
        small = daisy_image[::2, ::2]
        rows.append(("segments (slic)", best_of(lambda: slic.masks(small), repeats)))
    rows.append(("vocabulary assign", best_of(lambda: assign(features, centres), repeats)))
    rows.append(("anyloc vlad", best_of(lambda: vlad(features, centres), repeats)))
    membership = mask_patch_membership(masks, image_size, (h, w), patch)
    rows.append(
        (
            "mask -> patches",
            best_of(lambda: mask_patch_membership(masks, image_size, (h, w), patch), repeats),
        )
    )
    adjacency = segment_adjacency(segment_centroids(masks))
    rows.append(
        ("segment graph", best_of(lambda: segment_adjacency(segment_centroids(masks)), repeats))
    )
    regions = (neighbourhood(adjacency, 3).astype(np.float32) @ membership) > 0
    rows.append(
        (
            "order-3 neighbourhoods",
            best_of(
                lambda: (neighbourhood(adjacency, 3).astype(np.float32) @ membership) > 0, repeats
            ),
        )
    )
    fast = vlad_per_region(features, regions, centres)
    rows.append(
        (
            "segvlad descriptors",
            best_of(lambda: vlad_per_region(features, regions, centres), repeats),
        )
    )
    start = time.perf_counter()
    direct = direct_segvlad(features, regions, centres)
    direct_ms = (time.perf_counter() - start) * 1000
    rows.append(("segvlad direct float64 loop", direct_ms))
    error = float(np.abs(fast - direct).max())
    pca = fit_pca(rng.standard_normal((2000, fast.shape[1])).astype(np.float32), 256)
    rows.append(("pca transform (256)", best_of(lambda: pca.transform(fast), repeats)))
    print(f"\n{name}: {h} x {w} patches x {dim}, {n_segments} masks at {mask_size}, order 3")
    print(f"  mean patches per order-3 region: {regions.sum(1).mean():.0f} of {h * w}")
    print(f"  {'stage':32s} {'ms / image':>10s}")
    print(f"  {'-' * 43}")
    for stage, ms in rows:
        print(f"  {stage:32s} {ms:10.2f}")
    print(f"  fast vs direct max |difference|: {error:.1e}")
    return fast


def bench_retrieval(rng, n_images: int = 406):
    n_ref_images, n_query_images, per_image, dim = n_images, n_images, 85, 1024
    ref = l2_normalize(rng.standard_normal((n_ref_images * per_image, dim)).astype(np.float32))
    query = l2_normalize(rng.standard_normal((n_query_images * per_image, dim)).astype(np.float32))
    start = time.perf_counter()
    distances, indices = flat_knn(ref, query, 50)
    search_s = time.perf_counter() - start
    owner = np.repeat(np.arange(n_ref_images), per_image)
    start = time.perf_counter()
    query_owner = np.repeat(np.arange(n_query_images), per_image)
    vote_ranking(distances, indices, query_owner, owner, n_query_images, n_ref_images, 50)
    vote_s = time.perf_counter() - start
    print(f"\nretrieval ({n_images} + {n_images} images x 85 segments, PCA 1024):")
    print(f"  faiss top-50 search of {len(query)} segments: {search_s:.2f} s total")
    print(f"  sparse voting and ranking (top 50): {vote_s * 1000:.0f} ms total")


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument(
        "--smoke", action="store_true", help="corridor shapes, one repeat, 20 + 20 images searched"
    )
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    image = rng.uniform(0, 1, (120, 160, 3)).astype(np.float32)
    repeats = 1 if args.smoke else args.repeats
    bench("corridor", (15, 20), 104, 40, (60, 80), 8, repeats, rng, daisy_image=image)
    if not args.smoke:
        bench("dinov2-g", (34, 45), 1536, 85, (240, 320), 14, repeats, rng)
    bench_retrieval(rng, 20 if args.smoke else 406)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"\npeak resident memory of this script: {peak:.0f} MiB")


if __name__ == "__main__":
    main()
