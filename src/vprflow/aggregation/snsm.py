"""SNSM: spatial neighbourhood support maps (docs/methods.md §6).

A dense token grid ``X [h, w, D]`` becomes a global descriptor in four steps:

1. normalisation (:func:`normalize_tokens`): ``"channel"`` (default, the published quirk)
   divides every channel by its L2 norm over all tokens of the image; ``"token"`` divides
   every token by its L2 norm over channels; ``"none"`` leaves ``X`` alone;
2. nearest-neighbour upscale by an integer factor ``u``: ``U[i, j] = X[i // u, j // u]``
   (identical to ``torch.nn.functional.interpolate(mode="nearest")`` for the integer
   factors used by the authors);
3. non-overlapping ``w x w`` windows of ``U``, each concatenated into one vector
   (:func:`window_grid`): ``P[m, n] = concat_{a, b} U[m*w + a, n*w + b, :]`` with the window
   offsets ``(a, b)`` in row-major order and channels fastest, i.e. the einops pattern
   ``"(h a) (w b) c -> h w (a b c)"`` used by the published code. (The order cannot change
   the result: any fixed permutation of coordinates preserves cosines and distances.)
4. support map (:func:`support_map`): ``S[m, n] = sum over neighbour offsets (k, l) of
   sim(P[m, n], P[m+k, n+l])``; neighbours outside the grid contribute 0 (so border cells
   sum fewer terms). ``S`` flattened row-major is the descriptor, not normalised.

The published code loops over every grid cell in Python. Here no Python loop runs over
cells, and each unordered neighbour pair is evaluated once (``sim`` is symmetric: the value
for offset ``(k, l)`` at ``(m, n)`` is the value for ``(-k, -l)`` at ``(m+k, n+l)``).
Two equivalent implementations:

- :func:`support_map` works on an explicit window grid ``P`` (:func:`window_grid`) with one
  shifted-array product over the whole grid per neighbour offset;
- :func:`snsm_descriptor` never builds ``P``. Because the upscale is nearest-neighbour,
  every element of a window vector is a token, so ``P[m, n] . P[m', n']`` and
  ``|P[m, n] - P[m', n']|^2`` are sums over the ``window x window`` element positions of
  token-level dot products / squared distances ``f(X[r, c], X[r + dr, c + dc])``. Only
  two token shifts ``dr`` per axis occur for a neighbour offset (``floor`` and ``ceil`` of
  ``k * window / u``), so a handful of shifted products over the small ``h x w x D`` grid,
  gathered and summed per window, give every similarity. This is exact (no cancellation:
  squared distances are summed from non-negative token terms), runs in float64, and
  needs memory of the order of the token grid instead of ``u^2`` times it.
"""

from __future__ import annotations

import numbers

import numpy as np

NORMALIZATIONS = ("channel", "token", "none")
SIMILARITIES = ("cosine", "neg_l2", "l2")

# One offset of each symmetric pair (k, l) / (-k, -l); support_map adds both directions.
_HALF_OFFSETS = {
    "diagonal4": ((1, 1), (1, -1)),
    "all8": ((0, 1), (1, 0), (1, 1), (1, -1)),
}
NEIGHBOURHOODS = tuple(_HALF_OFFSETS)

# The published channel normalisation divides by (norm + 1e-10) (lpips.normalize_tensor).
_CHANNEL_EPS = 1e-10
# Per-token normalisation follows torch.nn.functional.normalize: x / max(norm, 1e-12).
_TOKEN_EPS = 1e-12
# torch.nn.CosineSimilarity's default eps guards zero-length vectors.
_COSINE_EPS = 1e-8


def _check_choice(name: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ValueError(f"unknown {name} {value!r}; expected one of {', '.join(choices)}")


def _check_positive_int(name: str, value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def normalize_tokens(tokens: np.ndarray, normalization: str = "channel") -> np.ndarray:
    """L2-normalise one image's tokens.

    Args:
        tokens: ``[..., D]`` float array for ONE image; every leading axis is a token axis
            (``[h, w, D]`` or ``[N, D]``).
        normalization: ``"channel"``: each channel divided by ``(its L2 norm over all
            tokens + 1e-10)``, the published SNSM quirk; ``"token"``: each token divided by
            ``max(its L2 norm over channels, 1e-12)``; ``"none"``: unchanged.

    Returns:
        float32 array of the same shape.
    """
    _check_choice("normalization", normalization, NORMALIZATIONS)
    x = np.asarray(tokens, dtype=np.float64)
    if x.ndim < 2:
        raise ValueError(f"tokens must have a token axis and a channel axis, got {x.shape}")
    if normalization == "channel":
        norms = np.sqrt(np.sum(x * x, axis=tuple(range(x.ndim - 1)), keepdims=True))
        x = x / (norms + _CHANNEL_EPS)
    elif normalization == "token":
        norms = np.sqrt(np.sum(x * x, axis=-1, keepdims=True))
        x = x / np.maximum(norms, _TOKEN_EPS)
    return x.astype(np.float32)


def snsm_grid_shape(h: int, w: int, upscale: int = 4, window: int = 2) -> tuple[int, int]:
    """Support-map shape ``(h*u/window, w*u/window)`` for an ``h x w`` token grid.

    Raises ValueError when an upscaled side is not a multiple of ``window`` (the
    published einops rearrangement fails there too; silently cropping would drop
    border tokens).
    """
    upscale = _check_positive_int("upscale", upscale)
    window = _check_positive_int("window", window)
    h = _check_positive_int("grid height", h)
    w = _check_positive_int("grid width", w)
    if (h * upscale) % window or (w * upscale) % window:
        raise ValueError(
            f"window {window} does not divide the upscaled grid {h * upscale} x {w * upscale}"
            f" (token grid {h} x {w}, upscale {upscale})"
        )
    return h * upscale // window, w * upscale // window


def _element_tokens(cells: int, upscale: int, window: int) -> np.ndarray:
    """``[cells, window]`` token index along one axis of every window element."""
    return (np.arange(cells)[:, None] * window + np.arange(window)[None, :]) // upscale


def window_grid(tokens: np.ndarray, upscale: int = 4, window: int = 2) -> np.ndarray:
    """Upscale (nearest) and cut into concatenated windows.

    Args:
        tokens: ``[h, w, D]`` (already normalised as wanted).

    Returns:
        float32 ``P [h*u/window, w*u/window, window*window*D]`` with
        ``P[m, n, (a*window + b)*D + d] = tokens[(m*window + a) // u, (n*window + b) // u, d]``.
    """
    x = np.asarray(tokens, dtype=np.float32)
    if x.ndim != 3:
        raise ValueError(f"tokens must be [h, w, D], got shape {x.shape}")
    h, w, depth = x.shape
    rows, cols = snsm_grid_shape(h, w, upscale, window)
    row_index = _element_tokens(rows, upscale, window)
    col_index = _element_tokens(cols, upscale, window)
    # Gather P straight from the token grid: the upscaled grid U is never materialised.
    gathered = x[row_index[:, None, :, None], col_index[None, :, None, :]]
    # gathered is [rows, cols, a, b, D] and C-contiguous, so this reshape is free.
    return gathered.reshape(rows, cols, window * window * depth)


def _overlap(offset: int, size: int) -> tuple[slice, slice]:
    """Slices of cells that have an in-grid neighbour at ``offset``, and those neighbours."""
    cells = slice(max(0, -offset), size - max(0, offset))
    neighbours = slice(max(0, offset), size + min(0, offset))
    return cells, neighbours


def support_map(
    grid: np.ndarray, neighbourhood: str = "diagonal4", similarity: str = "cosine"
) -> np.ndarray:
    """Neighbourhood support ``S[m, n] = sum_{(k, l)} sim(P[m, n], P[m+k, n+l])``.

    Args:
        grid: ``P [H, W, L]`` window vectors (see :func:`window_grid`).
        neighbourhood: ``"diagonal4"`` = offsets (+-1, +-1) (published default);
            ``"all8"`` = all 8 neighbours (published ablation).
        similarity: ``"cosine"`` = ``a.b / max(|a||b|, 1e-8)`` (published default);
            ``"neg_l2"`` = ``-|a - b|``; ``"l2"`` = ``+|a - b|``, which is what the
            published Euclidean ablation sums (it differs from ``neg_l2`` only in the
            sign of the whole descriptor, so L2 retrieval ranks identically).

    Returns:
        float32 ``[H, W]``; out-of-grid neighbours contribute 0. (The published ``all8``
        ablation sums the 3 x 3 block including the centre and subtracts 1; that equals
        ``all8`` here except at an all-zero window vector, where it gives -1, not 0.)
    """
    _check_choice("neighbourhood", neighbourhood, NEIGHBOURHOODS)
    _check_choice("similarity", similarity, SIMILARITIES)
    p = np.asarray(grid, dtype=np.float32)
    if p.ndim != 3:
        raise ValueError(f"grid must be [H, W, L], got shape {p.shape}")
    rows, cols, _ = p.shape
    # Products are accumulated in float64 (einsum buffers the cast chunk-wise, no full
    # copy of P): float32 sums over thousands of channels would lose ~1e-5 relative.
    support = np.zeros((rows, cols), dtype=np.float64)
    if similarity == "cosine":
        norms = np.sqrt(np.einsum("ijk,ijk->ij", p, p, dtype=np.float64))
    for dk, dl in _HALF_OFFSETS[neighbourhood]:
        src_r, dst_r = _overlap(dk, rows)
        src_c, dst_c = _overlap(dl, cols)
        a = p[src_r, src_c]
        b = p[dst_r, dst_c]
        if similarity == "cosine":
            dots = np.einsum("ijk,ijk->ij", a, b, dtype=np.float64)
            values = dots / np.maximum(norms[src_r, src_c] * norms[dst_r, dst_c], _COSINE_EPS)
        else:
            # The difference is formed explicitly: |a|^2 + |b|^2 - 2a.b cancels badly for
            # neighbours that share most upscaled tokens (distance near 0).
            diff = a - b
            values = np.sqrt(np.einsum("ijk,ijk->ij", diff, diff, dtype=np.float64))
            del diff
            if similarity == "neg_l2":
                values = -values
        support[src_r, src_c] += values
        support[dst_r, dst_c] += values
    return support.astype(np.float32)


def _token_pairs(x: np.ndarray, dr: int, dc: int, squared_distance: bool) -> np.ndarray:
    """``[h, w]``: f(X[r, c], X[r+dr, c+dc]) (dot or squared distance); 0 without partner."""
    h, w, _ = x.shape
    out = np.zeros((h, w), dtype=np.float64)
    cells_r, partners_r = _overlap(dr, h)
    cells_c, partners_c = _overlap(dc, w)
    a = x[cells_r, cells_c]
    b = x[partners_r, partners_c]
    if squared_distance:
        diff = a - b
        out[cells_r, cells_c] = np.einsum("ijk,ijk->ij", diff, diff)
    else:
        out[cells_r, cells_c] = np.einsum("ijk,ijk->ij", a, b)
    return out


def _support_from_tokens(
    x: np.ndarray, upscale: int, window: int, neighbourhood: str, similarity: str
) -> np.ndarray:
    """Support map ``[rows, cols]`` (float64) of float64 tokens ``x [h, w, D]``, without P."""
    h, w, _ = x.shape
    rows, cols = snsm_grid_shape(h, w, upscale, window)
    row_tokens = _element_tokens(rows, upscale, window)
    col_tokens = _element_tokens(cols, upscale, window)

    def window_sum(table: np.ndarray, r_index: np.ndarray, c_index: np.ndarray) -> np.ndarray:
        # A per-token table [h, w] gathered at every window element, summed per window.
        return table[r_index[:, None, :, None], c_index[None, :, None, :]].sum(axis=(2, 3))

    cosine = similarity == "cosine"
    if cosine:
        norms = np.sqrt(window_sum(np.einsum("ijk,ijk->ij", x, x), row_tokens, col_tokens))
    support = np.zeros((rows, cols), dtype=np.float64)
    for dk, dl in _HALF_OFFSETS[neighbourhood]:
        cells_r, partners_r = _overlap(dk, rows)
        cells_c, partners_c = _overlap(dl, cols)
        r0, c0 = row_tokens[cells_r], col_tokens[cells_c]
        if r0.size == 0 or c0.size == 0:
            continue
        # Token shift of each window element between a cell and its neighbour; only a
        # couple of distinct values occur, one shifted product over X for each pair.
        shifts_r, which_r = np.unique(row_tokens[partners_r] - r0, return_inverse=True)
        shifts_c, which_c = np.unique(col_tokens[partners_c] - c0, return_inverse=True)
        tables = np.stack(
            [
                np.stack([_token_pairs(x, int(dr), int(dc), not cosine) for dc in shifts_c])
                for dr in shifts_r
            ]
        )
        which_r = which_r.reshape(r0.shape)
        which_c = which_c.reshape(c0.shape)
        pair = tables[
            which_r[:, None, :, None],
            which_c[None, :, None, :],
            r0[:, None, :, None],
            c0[None, :, None, :],
        ].sum(axis=(2, 3))
        if cosine:
            scale = norms[cells_r, cells_c] * norms[partners_r, partners_c]
            values = pair / np.maximum(scale, _COSINE_EPS)
        else:
            values = np.sqrt(pair)
            if similarity == "neg_l2":
                values = -values
        support[cells_r, cells_c] += values
        support[partners_r, partners_c] += values
    return support


def snsm_descriptor(
    tokens: np.ndarray,
    upscale: int = 4,
    window: int = 2,
    neighbourhood: str = "diagonal4",
    similarity: str = "cosine",
    normalization: str = "channel",
) -> np.ndarray:
    """SNSM global descriptor of one image.

    Args:
        tokens: ``[h, w, D]`` patch tokens (CLS excluded).
        upscale: nearest-neighbour upscale factor ``u`` (published default 4).
        window: window side ``w``; must divide ``h*u`` and ``w*u`` (ValueError otherwise).
        neighbourhood, similarity: see :func:`support_map`.
        normalization: see :func:`normalize_tokens`; applied on the token grid before
            upscaling, as published.

    Returns:
        float32 ``[(h*u/window) * (w*u/window)]``, the support map flattened row-major.
    """
    _check_choice("normalization", normalization, NORMALIZATIONS)
    _check_choice("neighbourhood", neighbourhood, NEIGHBOURHOODS)
    _check_choice("similarity", similarity, SIMILARITIES)
    x = np.asarray(tokens)
    if x.ndim != 3:
        raise ValueError(f"tokens must be [h, w, D], got shape {x.shape}")
    # Normalised tokens are rounded to float32 first so that this path and
    # support_map(window_grid(...)) see exactly the same values.
    normalised = normalize_tokens(x, normalization).astype(np.float64)
    support = _support_from_tokens(normalised, upscale, window, neighbourhood, similarity)
    return support.astype(np.float32).reshape(-1)
