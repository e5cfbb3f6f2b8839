"""SegVLAD: VLAD descriptors of segments and their graph neighbourhoods.

Per image: masks ``[S, Hm, Wm]`` at segmentation resolution, patch descriptors
``[N = h * w, D]`` on the feature grid, VLAD centres ``[K, D]``. Steps
(docs/methods.md §5): masks -> patch membership ``M [S, N]``; centroid Delaunay graph ``A
[S, S]``; neighbourhood ``(A^k M) > 0``; VLAD of each neighbourhood -> ``[S, K * D]``.
At order 0 (``A^0 = I``) the graph is not built, and scipy, which only the Delaunay
triangulation needs, is not imported.
"""

from __future__ import annotations

import functools

import numpy as np

from vprflow.aggregation.vlad import vlad_per_region
from vprflow.core.arrays import center_offset
from vprflow.core.lazy import lazy_import

# scipy costs a job 120-330 ms to import (benchmarks/README.md, "Descriptors"), and only
# the Delaunay graph needs it, which order 0 never builds.
spatial = lazy_import("scipy.spatial")

# How images with 3 or fewer segments are linked (segment_adjacency); the config
# schema's segvlad.small_graph lists these.
SMALL_GRAPHS = ("published", "complete")


def _source_index(n_out: int, n_in: int) -> np.ndarray:
    """Nearest-neighbour upsampling map (torch ``interpolate(mode='nearest')``)."""
    return np.minimum((np.arange(n_out) * n_in) // n_out, n_in - 1)


def _patch_of_pixel(n_pixels: int, n_patches: int, patch_size: int, offset: int) -> np.ndarray:
    """Patch index of each pixel row (or column); -1 for pixels outside the grid."""
    index = (np.arange(n_pixels) - offset) // patch_size
    if offset == 0:
        # Published mapping: uncropped coordinates, the remainder clipped to the last patch.
        return np.minimum(index, n_patches - 1)
    return np.where((np.arange(n_pixels) >= offset) & (index < n_patches), index, -1)


@functools.lru_cache(maxsize=16)
def _source_table(
    n_pixels: int, n_mask: int, n_patches: int, patch_size: int, offset: int
) -> np.ndarray:
    """Mask rows (or columns) each patch row (column) sees after nearest upsampling:
    int ``[G, n_patches]``, column ``i`` listing patch ``i``'s mask rows, the last one
    repeated up to the longest list's length ``G``.

    ORing over these few mask rows equals ORing over the patch's pixels of an upsampled
    mask, without building that mask; repeating a row does not change an OR, and a
    rectangular table lets one fancy index gather every patch's rows at once. Each
    patch's rows are consecutive (both maps are monotone). Cached: it depends only on
    the shapes, the same for every image of a stage.
    """
    source = _source_index(n_pixels, n_mask)
    patch = _patch_of_pixel(n_pixels, n_patches, patch_size, offset)
    keep = patch >= 0
    pairs = np.unique(patch[keep].astype(np.int64) * n_mask + source[keep])
    owners, sources = np.divmod(pairs, n_mask)
    if not np.array_equal(np.unique(owners), np.arange(n_patches)):
        raise ValueError(f"{n_patches} patches of {patch_size} px do not fit in {n_pixels} px")
    starts = np.searchsorted(owners, np.arange(n_patches))
    stops = np.append(starts[1:], len(sources))
    step = np.arange((stops - starts).max())[:, None]
    table = sources[np.minimum(starts + step, stops - 1)]
    table.flags.writeable = False  # shared by every caller (cache)
    return table


def mask_patch_membership(
    masks: np.ndarray,
    image_size: tuple[int, int],
    grid: tuple[int, int],
    patch_size: int,
    crop_aligned: bool = False,
) -> np.ndarray:
    """Which patches each mask touches: bool ``[S, h * w]``.

    ``masks`` ``[S, Hm, Wm]`` are upsampled (nearest) to the feature image
    ``image_size = (H, W)``; patch ``(i, j)`` belongs to a mask if any of its pixels
    does. By default pixel rows ``i * p .. i * p + p - 1`` form patch row ``i`` in
    uncropped coordinates, the leftover rows joining the last patch (the published
    quirk). ``crop_aligned=True`` instead shifts by the centre-crop offset and ignores
    pixels outside the crop.
    """
    height, width = image_size
    h, w = grid
    masks = np.ascontiguousarray(masks, dtype=bool)
    if len(masks) == 0:
        return np.zeros((0, h * w), dtype=bool)
    # The grid's own centre crop (the backbone's, when the grid covers the image).
    top = center_offset(height, h * patch_size) if crop_aligned else 0
    left = center_offset(width, w * patch_size) if crop_aligned else 0
    rows = _source_table(height, masks.shape[1], h, patch_size, top)  # [Gr, h]
    cols = _source_table(width, masks.shape[2], w, patch_size, left)  # [Gc, w]
    # OR as bitwise_or.reduce over uint8 (bool's bytes are 0 or 1) along a middle axis:
    # whole rows at a time, ~10x faster than logical_or.reduceat over many short groups.
    bits = masks.view(np.uint8)
    cells = np.bitwise_or.reduce(bits[:, rows], axis=1)  # [S, Gr, h, Wm] -> [S, h, Wm]
    cells = np.bitwise_or.reduce(cells[:, :, cols], axis=2)  # [S, h, Gc, w] -> [S, h, w]
    return cells.reshape(len(masks), h * w).view(bool)


def segment_centroids(masks: np.ndarray) -> np.ndarray:
    """Mean ``(x, y)`` pixel position of each mask ``[S, H, W]`` -> ``[S, 2]`` float64.

    An empty mask gets NaN coordinates.
    """
    # Integer pixel counts per column and row (summing bool would widen to int64 first,
    # twice as slow), then exact float64 weighted sums.
    bits = np.ascontiguousarray(masks, dtype=bool).view(np.uint8)
    columns = bits.sum(axis=1, dtype=np.int32)  # [S, W]
    rows = bits.sum(axis=2, dtype=np.int32)  # [S, H]
    area = columns.sum(axis=1).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        cx = (columns @ np.arange(bits.shape[2], dtype=np.float64)) / area
        cy = (rows @ np.arange(bits.shape[1], dtype=np.float64)) / area
    return np.stack([cx, cy], axis=1)


def check_small_graph(small_graph: str) -> None:
    """Raise unless ``small_graph`` is one of :data:`SMALL_GRAPHS`: checked for every
    image, whatever its number of segments and the order, so that a wrong name fails
    on the first image rather than on the first with 3 or fewer segments."""
    if small_graph not in SMALL_GRAPHS:
        raise ValueError(f"unknown small_graph {small_graph!r}; expected one of {SMALL_GRAPHS}")


def segment_adjacency(centroids: np.ndarray, small_graph: str = "published") -> np.ndarray:
    """Delaunay graph of segment centroids with self loops: bool ``[S, S]``.

    With 3 or fewer segments no triangulation is built; ``small_graph='published'``
    reproduces the authors' code (every segment linked to segments 0 and 1 only,
    not necessarily to itself), ``'complete'`` links all of them. Collinear or
    otherwise degenerate centroids fall back to linking consecutive centroids in
    sorted order along their line (the 1-D Delaunay graph).
    """
    check_small_graph(small_graph)
    n = len(centroids)
    adjacency = np.eye(n, dtype=bool)
    if n <= 3:
        if small_graph == "published":
            adjacency[:] = False
            adjacency[:, : min(n, 2)] = True
        else:  # "complete"
            adjacency[:] = True
        return adjacency
    points = np.nan_to_num(np.asarray(centroids, dtype=np.float64), nan=-1.0)
    try:
        indptr, indices = spatial.Delaunay(points).vertex_neighbor_vertices
    except spatial.QhullError:
        order = np.lexsort((points[:, 1], points[:, 0]))
        adjacency[order[:-1], order[1:]] = True
        adjacency[order[1:], order[:-1]] = True
        return adjacency
    adjacency[np.repeat(np.arange(n), np.diff(indptr)), indices] = True
    return adjacency


def neighbourhood(adjacency: np.ndarray, order: int) -> np.ndarray:
    """Boolean ``order``-th power of ``adjacency``: segments within ``order`` hops.

    ``order = 0`` is the identity (each segment alone).
    """
    reach = np.eye(len(adjacency), dtype=bool)
    step = adjacency.astype(np.float32)
    for _ in range(order):
        reach = (reach.astype(np.float32) @ step) > 0
    return reach


def image_segvlad(
    features: np.ndarray,
    masks: np.ndarray,
    centres: np.ndarray,
    image_size: tuple[int, int],
    patch_size: int,
    order: int,
    crop_aligned: bool = False,
    small_graph: str = "published",
) -> np.ndarray:
    """SegVLAD descriptors of one image: ``features [h, w, D]``, ``masks [S, Hm, Wm]``
    -> ``[S, K * D]``."""
    h, w, d = features.shape
    membership = mask_patch_membership(masks, image_size, (h, w), patch_size, crop_aligned)
    regions = segment_regions(masks, membership, order, small_graph)
    return vlad_per_region(features.reshape(h * w, d), regions, centres)


def segment_regions(
    masks: np.ndarray, membership: np.ndarray, order: int, small_graph: str = "published"
) -> np.ndarray:
    """The patches each segment's descriptor aggregates, ``(A^order M) > 0``: bool
    ``[S, N]`` from ``masks [S, Hm, Wm]`` (for the graph ``A``) and their membership
    ``M [S, N]``.

    At order 0 this is ``M`` itself, returned as it is: ``A^0`` is the identity whatever
    ``A`` holds (the published small-graph quirk, which may leave a segment without its
    self loop, included), and ``I M`` in float32 is ``M`` exactly. So the graph is not
    built there: no centroids, no Delaunay triangulation per image, no scipy import.
    """
    check_small_graph(small_graph)
    if order == 0:
        return membership
    adjacency = segment_adjacency(segment_centroids(masks), small_graph)
    return (neighbourhood(adjacency, order).astype(np.float32) @ membership) > 0
