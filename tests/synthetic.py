"""A small synthetic place dataset: each place is a random arrangement of coloured
shapes; its query is the reference shifted a few pixels, re-lit and noised."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image


def place_image(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    image = np.full((height, width, 3), rng.uniform(0.2, 0.8, 3), dtype=np.float64)
    yy, xx = np.mgrid[0:height, 0:width]
    for _ in range(8):
        colour = rng.uniform(0, 1, 3)
        cx, cy = rng.uniform(0, width), rng.uniform(0, height)
        if rng.random() < 0.5:
            r = rng.uniform(4, height / 3)
            inside = (xx - cx) ** 2 + (yy - cy) ** 2 < r**2
        else:
            a, b = rng.uniform(4, width / 3), rng.uniform(4, height / 3)
            inside = (abs(xx - cx) < a) & (abs(yy - cy) < b)
        image[inside] = colour
    # Real scenes are textured; flat synthetic regions give gradient-free descriptors.
    from scipy.ndimage import gaussian_filter

    texture = gaussian_filter(rng.normal(0, 1, (height, width)), 1.0)
    return np.clip(image + 0.15 * texture[:, :, None], 0, 1)


def write_vprbench_ground_truth(path: Path, n_query: int, n_ref: int, radius: int = 1) -> None:
    rows = np.empty((n_query, 2), dtype=object)
    for q in range(n_query):
        rows[q, 0] = q
        rows[q, 1] = list(range(max(0, q - radius), min(n_ref, q + radius + 1)))
    np.save(path, rows, allow_pickle=True)


def make_dataset(
    root: Path, n_places: int = 10, width: int = 96, height: int = 72, seed: int = 0
) -> Path:
    """Write ``root/ref``, ``root/query`` and ``root/ground_truth_new.npy``; returns root."""
    rng = np.random.default_rng(seed)
    (root / "ref").mkdir(parents=True, exist_ok=True)
    (root / "query").mkdir(parents=True, exist_ok=True)
    for i in range(n_places):
        image = place_image(rng, width + 8, height + 8)
        dx, dy = rng.integers(0, 8, 2)
        ref = image[4 : 4 + height, 4 : 4 + width]
        query = image[dy : dy + height, dx : dx + width] * rng.uniform(0.8, 1.1)
        query = np.clip(query + rng.normal(0, 0.03, query.shape), 0, 1)
        Image.fromarray((ref * 255).astype(np.uint8)).save(root / "ref" / f"{i:04d}.png")
        Image.fromarray((query * 255).astype(np.uint8)).save(root / "query" / f"{i:04d}.jpg")
    write_vprbench_ground_truth(root / "ground_truth_new.npy", n_places, n_places)
    return root
