"""SNSM support maps against a direct float64 transcription of REFERENCE.md section 3.

Tolerance: the library works in float32 with float64 accumulation of the dot products,
the reference below is float64 throughout; we require rtol 1e-5 plus atol 1e-5 times
the typical magnitude of one similarity term (1 for cosine, the mean neighbour distance
for the Euclidean variants), which covers cells whose terms cancel to nearly 0.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from vprflow.aggregation.snsm import (
    normalize_tokens,
    snsm_descriptor,
    snsm_grid_shape,
    support_map,
    window_grid,
)

DIAGONAL4 = [(-1, -1), (-1, 1), (1, -1), (1, 1)]
ALL8 = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if (dr, dc) != (0, 0)]


def direct_normalize(x: np.ndarray, normalization: str) -> np.ndarray:
    h, w, depth = x.shape
    out = x.copy()
    if normalization == "channel":
        for d in range(depth):
            norm = math.sqrt(sum(x[i, j, d] ** 2 for i in range(h) for j in range(w)))
            out[:, :, d] = x[:, :, d] / (norm + 1e-10)
    elif normalization == "token":
        for i in range(h):
            for j in range(w):
                out[i, j] = x[i, j] / max(math.sqrt(float(np.dot(x[i, j], x[i, j]))), 1e-12)
    return out


def direct_upscale(x: np.ndarray, u: int) -> np.ndarray:
    h, w, depth = x.shape
    out = np.empty((h * u, w * u, depth))
    for i in range(h * u):
        for j in range(w * u):
            out[i, j] = x[i // u, j // u]
    return out


def direct_windows(up: np.ndarray, win: int) -> list[list[np.ndarray]]:
    rows, cols = up.shape[0] // win, up.shape[1] // win
    grid = []
    for m in range(rows):
        row = []
        for n in range(cols):
            parts = []
            for a in range(win):  # row-major inside the window, channels fastest
                for b in range(win):
                    parts.append(up[m * win + a, n * win + b])
            row.append(np.concatenate(parts))
        grid.append(row)
    return grid


def direct_sim(p: np.ndarray, q: np.ndarray, similarity: str) -> float:
    if similarity == "cosine":
        return float(np.dot(p, q)) / max(
            math.sqrt(float(np.dot(p, p))) * math.sqrt(float(np.dot(q, q))), 1e-8
        )
    dist = math.sqrt(float(np.dot(p - q, p - q)))
    return -dist if similarity == "neg_l2" else dist


def direct_snsm(x, u, win, neighbourhood, similarity, normalization) -> np.ndarray:
    x = direct_normalize(np.asarray(x, dtype=np.float64), normalization)
    grid = direct_windows(direct_upscale(x, u), win)
    offsets = DIAGONAL4 if neighbourhood == "diagonal4" else ALL8
    rows, cols = len(grid), len(grid[0])
    support = np.zeros((rows, cols))
    for m in range(rows):
        for n in range(cols):
            for dr, dc in offsets:
                if 0 <= m + dr < rows and 0 <= n + dc < cols:
                    support[m, n] += direct_sim(grid[m][n], grid[m + dr][n + dc], similarity)
    return support.reshape(-1)


def assert_close(fast: np.ndarray, slow: np.ndarray, similarity: str, scale: float) -> None:
    assert fast.dtype == np.float32
    assert fast.shape == slow.shape
    np.testing.assert_allclose(fast, slow, rtol=1e-5, atol=1e-5 * scale)


def term_scale(x, u, win, similarity, normalization) -> float:
    if similarity == "cosine":
        return 1.0
    grid = window_grid(normalize_tokens(x, normalization), u, win).astype(np.float64)
    return float(np.mean(np.linalg.norm(grid, axis=-1))) + 1e-12


CASES = [
    # (h, w, D, u, win, neighbourhood, similarity, normalization)
    (4, 4, 6, 4, 2, "diagonal4", "cosine", "channel"),  # the published setting, small
    (3, 5, 7, 2, 2, "diagonal4", "cosine", "channel"),  # non-square
    (5, 3, 4, 3, 3, "all8", "cosine", "token"),
    (4, 6, 5, 1, 1, "all8", "neg_l2", "none"),  # no upscale, single-token windows
    (4, 6, 6, 3, 2, "diagonal4", "neg_l2", "channel"),  # window straddles token borders
    (2, 6, 3, 5, 5, "all8", "l2", "token"),
    (4, 4, 8, 4, 4, "diagonal4", "l2", "none"),
    (2, 3, 5, 6, 2, "all8", "cosine", "none"),
    (6, 4, 3, 2, 4, "diagonal4", "cosine", "token"),
]


@pytest.mark.parametrize("h,w,depth,u,win,neighbourhood,similarity,normalization", CASES)
def test_matches_direct_formula(h, w, depth, u, win, neighbourhood, similarity, normalization):
    rng = np.random.default_rng(h * 1000 + w * 100 + depth * 10 + u)
    x = rng.standard_normal((h, w, depth)).astype(np.float32)
    fast = snsm_descriptor(x, u, win, neighbourhood, similarity, normalization)
    slow = direct_snsm(x, u, win, neighbourhood, similarity, normalization)
    assert_close(fast, slow, similarity, term_scale(x, u, win, similarity, normalization))


@pytest.mark.parametrize("h,w,depth,u,win,neighbourhood,similarity,normalization", CASES)
def test_window_grid_path_matches_direct_formula(
    h, w, depth, u, win, neighbourhood, similarity, normalization
):
    rng = np.random.default_rng(h * 1000 + w * 100 + depth * 10 + u + 1)
    x = rng.standard_normal((h, w, depth)).astype(np.float32)
    grid = window_grid(normalize_tokens(x, normalization), u, win)
    fast = support_map(grid, neighbourhood, similarity).reshape(-1)
    slow = direct_snsm(x, u, win, neighbourhood, similarity, normalization)
    assert_close(fast, slow, similarity, term_scale(x, u, win, similarity, normalization))


@pytest.mark.parametrize(
    "u,win,neighbourhood,similarity",
    [
        (4, 2, "diagonal4", "cosine"),
        (6, 2, "all8", "neg_l2"),
        (4, 7, "diagonal4", "neg_l2"),
        (5, 2, "all8", "cosine"),
    ],
)
def test_token_path_matches_window_grid_path_at_published_size(u, win, neighbourhood, similarity):
    # Full 28 x 28 x 768 grids are too slow for the direct loops; the two vectorised
    # implementations (token-level gather vs explicit P) must agree there.
    x = np.random.default_rng(u * 10 + win).standard_normal((28, 28, 768)).astype(np.float32)
    ours = snsm_descriptor(x, u, win, neighbourhood, similarity)
    grid = window_grid(normalize_tokens(x, "channel"), u, win)
    other = support_map(grid, neighbourhood, similarity).reshape(-1)
    scale = 1.0 if similarity == "cosine" else float(np.mean(np.abs(other)))
    np.testing.assert_allclose(ours, other, rtol=1e-5, atol=1e-6 * scale)


def test_defaults_are_published_setting():
    rng = np.random.default_rng(7)
    x = rng.standard_normal((4, 3, 5)).astype(np.float32)
    expected = direct_snsm(x, 4, 2, "diagonal4", "cosine", "channel")
    np.testing.assert_allclose(snsm_descriptor(x), expected, rtol=1e-5, atol=1e-5)


def test_window_order_is_row_major_channels_fastest():
    h, w, depth, u, win = 2, 3, 2, 2, 2
    x = np.arange(h * w * depth, dtype=np.float32).reshape(h, w, depth)
    grid = window_grid(x, u, win)
    expected = np.array(direct_windows(direct_upscale(x.astype(np.float64), u), win))
    assert grid.shape == (h * u // win, w * u // win, win * win * depth)
    np.testing.assert_array_equal(grid, expected)
    # Element formula from the docstring, checked at one non-trivial position.
    m, n, a, b, d = 1, 2, 1, 0, 1
    assert grid[m, n, (a * win + b) * depth + d] == x[(m * win + a) // u, (n * win + b) // u, d]


@pytest.mark.parametrize("u", [2, 3, 4, 5, 6])
def test_upscale_matches_torch_nearest(u):
    # The published code upsamples with torch's nearest interpolation; window 1 exposes U.
    rng = np.random.default_rng(u)
    x = rng.standard_normal((5, 7, 3)).astype(np.float32)
    ours = window_grid(x, u, 1)
    ref = torch.nn.functional.interpolate(
        torch.from_numpy(x).permute(2, 0, 1)[None], scale_factor=u, mode="nearest"
    )[0].permute(1, 2, 0)
    np.testing.assert_array_equal(ours, ref.numpy())


def test_channel_normalisation_is_over_tokens():
    rng = np.random.default_rng(3)
    x = rng.standard_normal((3, 4, 5))
    chan = normalize_tokens(x, "channel")
    np.testing.assert_allclose(np.linalg.norm(chan.reshape(-1, 5), axis=0), 1.0, rtol=1e-6)
    tok = normalize_tokens(x, "token")
    np.testing.assert_allclose(np.linalg.norm(tok, axis=-1), 1.0, rtol=1e-6)
    np.testing.assert_array_equal(normalize_tokens(x, "none"), x.astype(np.float32))


def test_boundary_cells_get_fewer_neighbours():
    # Constant tokens: every neighbour has cosine 1, so S counts in-grid neighbours.
    x = np.ones((3, 4, 2), dtype=np.float32)
    s4 = snsm_descriptor(x, 2, 2, "diagonal4").reshape(3, 4)
    expected4 = np.array([[1, 2, 2, 1], [2, 4, 4, 2], [1, 2, 2, 1]], dtype=np.float32)
    np.testing.assert_allclose(s4, expected4, rtol=1e-6)
    s8 = snsm_descriptor(x, 2, 2, "all8").reshape(3, 4)
    expected8 = np.array([[3, 5, 5, 3], [5, 8, 8, 5], [3, 5, 5, 3]], dtype=np.float32)
    np.testing.assert_allclose(s8, expected8, rtol=1e-6)


def test_single_window_has_no_neighbours():
    x = np.random.default_rng(0).standard_normal((2, 2, 3))
    np.testing.assert_array_equal(snsm_descriptor(x, 2, 4), np.zeros(1, dtype=np.float32))


@pytest.mark.parametrize(
    "h,w,u,win", [(28, 28, 4, 2), (28, 28, 6, 2), (28, 28, 4, 7), (14, 20, 5, 2), (3, 5, 2, 1)]
)
def test_descriptor_length(h, w, u, win):
    expected = ((h * u) // win) * ((w * u) // win)
    assert snsm_grid_shape(h, w, u, win) == ((h * u) // win, (w * u) // win)
    if h * w * u * u <= 28 * 28 * 16:
        x = np.random.default_rng(1).standard_normal((h, w, 2)).astype(np.float32)
        assert snsm_descriptor(x, u, win).shape == (expected,)


def test_published_length_3136():
    rows, cols = snsm_grid_shape(28, 28)
    assert rows * cols == 3136


def test_support_map_is_symmetric_sum():
    # Swapping cells does not matter: total support = 2 * sum over unordered pairs.
    rng = np.random.default_rng(5)
    grid = rng.standard_normal((4, 5, 3)).astype(np.float32)
    s = support_map(grid, "diagonal4", "neg_l2")
    pairs = 0.0
    for m in range(3):
        for n in range(5):
            for dn in (-1, 1):
                if 0 <= n + dn < 5:
                    pairs -= np.linalg.norm(grid[m, n].astype(np.float64) - grid[m + 1, n + dn])
    np.testing.assert_allclose(s.sum(dtype=np.float64), 2 * pairs, rtol=1e-5)


@pytest.mark.parametrize(
    "kwargs,bad",
    [
        ({"neighbourhood": "cross4"}, "cross4"),
        ({"similarity": "dot"}, "dot"),
        ({"normalization": "l1"}, "l1"),
        ({"upscale": 0}, "0"),
        ({"window": -2}, "-2"),
        ({"upscale": 2.5}, "2.5"),
        ({"window": 3}, "window 3"),  # 7 * 4 = 28 is not a multiple of 3
    ],
)
def test_invalid_settings_name_the_value(kwargs, bad):
    x = np.zeros((7, 7, 2), dtype=np.float32)
    with pytest.raises(ValueError, match=bad):
        snsm_descriptor(x, **kwargs)


def test_rejects_wrong_rank():
    with pytest.raises(ValueError, match="h, w, D"):
        snsm_descriptor(np.zeros((4, 4), dtype=np.float32))
