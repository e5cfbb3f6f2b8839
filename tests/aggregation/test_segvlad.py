"""SegVLAD pieces (REFERENCE.md section 2, steps 3-5) against direct slow formulas.

Mask membership, centroids, graphs and neighbourhoods are exact (booleans / float64
means). Descriptors are float32 and compared with a float64 per-segment VLAD at 1e-5
absolute (entries of unit vectors); the random data are checked to have a clear
winning centre per patch (margin above 1e-4) so assignments cannot differ.
"""

from __future__ import annotations

import itertools
import math
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from scipy.spatial import Delaunay

from vprflow.aggregation import segvlad
from vprflow.aggregation.segvlad import (
    image_segvlad,
    mask_patch_membership,
    neighbourhood,
    segment_adjacency,
    segment_centroids,
    segment_regions,
)
from vprflow.aggregation.vlad import vlad_per_region

ATOL = 1e-5


# ------------------------------------------------------------ direct formulas


def direct_upsample(mask, height, width):
    """Nearest neighbour: destination pixel (y, x) reads source (y * Hm // H, x * Wm // W)."""
    hm, wm = mask.shape
    out = np.zeros((height, width), dtype=bool)
    for y in range(height):
        for x in range(width):
            out[y, x] = mask[(y * hm) // height, (x * wm) // width]
    return out


def direct_membership(masks, image_size, grid, patch, crop_aligned=False):
    height, width = image_size
    h, w = grid
    # the backbone's centre crop: offsets rounded half to even, like torchvision
    top = int(round((height - h * patch) / 2)) if crop_aligned else 0
    left = int(round((width - w * patch) / 2)) if crop_aligned else 0
    out = np.zeros((len(masks), h * w), dtype=bool)
    for s, mask in enumerate(masks):
        up = direct_upsample(mask, height, width)
        for y in range(height):
            for x in range(width):
                if not up[y, x]:
                    continue
                if crop_aligned:
                    if y < top or x < left:
                        continue
                    i, j = (y - top) // patch, (x - left) // patch
                    if i >= h or j >= w:
                        continue
                else:
                    i, j = min(y // patch, h - 1), min(x // patch, w - 1)
                out[s, i * w + j] = True
    return out


def direct_centroids(masks):
    out = []
    for mask in masks:
        xs, ys = [], []
        for y in range(mask.shape[0]):
            for x in range(mask.shape[1]):
                if mask[y, x]:
                    xs.append(x)
                    ys.append(y)
        out.append((sum(xs) / len(xs), sum(ys) / len(ys)) if xs else (math.nan, math.nan))
    return np.array(out, dtype=np.float64)


def direct_delaunay_adjacency(points):
    """Self loops plus every pair of vertices that share a Delaunay simplex."""
    n = len(points)
    adjacency = np.eye(n, dtype=bool)
    for simplex in Delaunay(points).simplices:
        for a, b in itertools.permutations(simplex, 2):
            adjacency[a, b] = True
    return adjacency


def direct_power(adjacency, k):
    """Boolean k-th power via repeated integer matrix products (k = 0: identity)."""
    a = np.asarray(adjacency, dtype=np.int64)
    power = np.eye(len(a), dtype=np.int64)
    for _ in range(k):
        power = (power @ a > 0).astype(np.int64)  # keep 0/1 so nothing can overflow
    return power > 0


def direct_assign(features, centres):
    centres = np.asarray(centres, np.float64)
    unit = centres / np.linalg.norm(centres, axis=1, keepdims=True)
    scores = np.asarray(features, np.float64) @ unit.T
    ordered = np.sort(scores, axis=1)
    return scores.argmax(axis=1), (ordered[:, -1] - ordered[:, -2]).min()


def direct_segvlad(features, regions, centres, labels):
    """Loop over segments; VLAD of the patches of each region, in float64."""
    features = np.asarray(features, np.float64)
    centres = np.asarray(centres, np.float64)
    k, d = centres.shape
    out = np.zeros((len(regions), k * d))
    for s, region in enumerate(regions):
        blocks = np.zeros((k, d))
        for p in np.flatnonzero(region):
            blocks[labels[p]] += features[p] - centres[labels[p]]
        for c in range(k):
            norm = math.sqrt(float(blocks[c] @ blocks[c]))
            if norm > 0:
                blocks[c] /= norm
        flat = blocks.ravel()
        norm = math.sqrt(float(flat @ flat))
        out[s] = flat / norm if norm > 0 else flat
    return out


def random_masks(rng, n, height, width, density=0.05):
    masks = rng.random((n, height, width)) < density
    masks[0] = False  # an empty mask
    if n > 1:
        masks[1] = False
        masks[1, rng.integers(height), rng.integers(width)] = True  # a single pixel
    return masks


def unit_rows(x):
    return x / np.linalg.norm(x, axis=1, keepdims=True)


# ------------------------------------------------------------ mask membership

# (mask size, feature image size, patch) -> grid = image // patch (the centre crop).
SIZES = [
    ((6, 8), (28, 42), 7),  # divisible by the patch, upsampled by non-integer factors
    ((12, 16), (24, 32), 8),  # divisible, exact factor 2
    ((7, 9), (31, 45), 7),  # not divisible: leftover rows and columns
    ((10, 13), (33, 50), 6),  # not divisible, odd leftovers (crop offsets 2 and 1)
    ((20, 20), (20, 20), 3),  # same size (no upsampling), 2 leftover pixels
    ((5, 5), (17, 23), 5),
]


@pytest.mark.parametrize("crop_aligned", [False, True])
@pytest.mark.parametrize(("mask_size", "image_size", "patch"), SIZES)
def test_mask_patch_membership_matches_direct_loop(mask_size, image_size, patch, crop_aligned):
    rng = np.random.default_rng(sum(mask_size) + sum(image_size) + patch)
    masks = random_masks(rng, 7, *mask_size)
    grid = (image_size[0] // patch, image_size[1] // patch)
    out = mask_patch_membership(masks, image_size, grid, patch, crop_aligned)
    assert out.shape == (7, grid[0] * grid[1]) and out.dtype == bool
    np.testing.assert_array_equal(
        out, direct_membership(masks, image_size, grid, patch, crop_aligned)
    )
    assert not out[0].any()  # empty mask touches nothing


def test_membership_modes_differ_where_the_crop_offset_matters():
    # A pixel in the first two rows belongs to patch row 0 uncropped (published quirk)
    # but lies outside the crop when the grid is centred (offset 2).
    masks = np.zeros((1, 30, 30), dtype=bool)
    masks[0, 0, 15] = True
    quirk = mask_patch_membership(masks, (30, 30), (4, 4), 6)
    aligned = mask_patch_membership(masks, (30, 30), (4, 4), 6, crop_aligned=True)
    assert quirk[0].sum() == 1 and quirk[0, 0 * 4 + 2]
    assert not aligned.any()
    # The last pixel row joins the last patch row in the quirk mode.
    masks[0] = False
    masks[0, 29, 0] = True
    assert mask_patch_membership(masks, (30, 30), (4, 4), 6)[0, 3 * 4 + 0]


# ------------------------------------------------------------ centroids and graph


def test_segment_centroids_are_mean_x_then_mean_y():
    rng = np.random.default_rng(1)
    masks = random_masks(rng, 9, 11, 17, density=0.2)
    out = segment_centroids(masks)
    expected = direct_centroids(masks)
    assert np.isnan(out[0]).all()
    np.testing.assert_allclose(out[1:], expected[1:], rtol=1e-12, atol=1e-12)
    one = np.zeros((1, 5, 9), dtype=bool)
    one[0, 1, 7] = True
    np.testing.assert_array_equal(segment_centroids(one), [[7.0, 1.0]])


@pytest.mark.parametrize("n", [4, 5, 8, 20, 60])
def test_adjacency_is_delaunay_with_self_loops(n):
    points = np.random.default_rng(n).uniform(0, 100, (n, 2))
    out = segment_adjacency(points)
    expected = direct_delaunay_adjacency(points)
    np.testing.assert_array_equal(out, expected)
    np.testing.assert_array_equal(out, out.T)
    assert out.diagonal().all()


@pytest.mark.parametrize("n", [1, 2, 3])
def test_small_graph_published_quirk_and_complete(n):
    points = np.random.default_rng(0).uniform(0, 100, (n, 2))
    published = segment_adjacency(points)
    expected = np.zeros((n, n), dtype=bool)
    for v in range(n):
        for u in (0, 1):
            if u < n:
                expected[v, u] = True
    np.testing.assert_array_equal(published, expected)
    if n == 3:
        assert not published[2, 2]  # segment 2 is not even linked to itself
    np.testing.assert_array_equal(
        segment_adjacency(points, small_graph="complete"), np.ones((n, n), bool)
    )
    with pytest.raises(ValueError, match="small_graph"):
        segment_adjacency(points, small_graph="nonsense")


@pytest.mark.parametrize("direction", [(1.0, 2.0), (0.0, 1.0), (1.0, 0.0)])
def test_collinear_centroids_link_consecutive_points(direction):
    rng = np.random.default_rng(2)
    t = rng.permutation(np.arange(7, dtype=np.float64) * 3.0 + rng.uniform(0, 1, 7))
    points = np.stack([5 + t * direction[0], 7 + t * direction[1]], axis=1)
    out = segment_adjacency(points)
    order = np.argsort(t)
    expected = np.eye(7, dtype=bool)
    for a, b in zip(order[:-1], order[1:], strict=True):
        expected[a, b] = expected[b, a] = True
    np.testing.assert_array_equal(out, expected)


# ------------------------------------------------------------ neighbourhoods


def random_graph(rng, n, symmetric=True):
    a = rng.random((n, n)) < 0.15
    if symmetric:
        a = a | a.T
        np.fill_diagonal(a, True)
    return a


@pytest.mark.parametrize("order", [0, 1, 2, 3, 4, 5])
@pytest.mark.parametrize("symmetric", [True, False])
def test_neighbourhood_is_boolean_matrix_power(order, symmetric):
    rng = np.random.default_rng(order + 10 * symmetric)
    for n in (1, 5, 17, 40):
        a = random_graph(rng, n, symmetric)
        out = neighbourhood(a, order)
        assert out.dtype == bool
        np.testing.assert_array_equal(out, direct_power(a, order))
    np.testing.assert_array_equal(neighbourhood(random_graph(rng, 6), 0), np.eye(6, dtype=bool))


def test_neighbourhood_of_a_path_grows_one_hop_per_order():
    n = 9
    path = np.eye(n, dtype=bool) | np.eye(n, k=1, dtype=bool) | np.eye(n, k=-1, dtype=bool)
    for order in range(6):
        hops = np.abs(np.subtract.outer(np.arange(n), np.arange(n)))
        np.testing.assert_array_equal(neighbourhood(path, order), hops <= order)


# ------------------------------------------------------------ descriptors


def descriptor_problem(seed, n_patches=60, k=5, d=12, n_regions=9):
    rng = np.random.default_rng(seed)
    features = unit_rows(rng.standard_normal((n_patches, d))).astype(np.float32)
    centres = (rng.standard_normal((k, d)) * rng.uniform(0.5, 2, (k, 1))).astype(np.float32)
    regions = rng.random((n_regions, n_patches)) < 0.3
    regions[0] = False  # empty region -> zero descriptor
    regions[1] = True  # whole image
    regions[2] = False
    regions[2, 3] = True  # a single patch
    return features, regions, centres


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_segvlad_descriptors_match_per_segment_direct_vlad(seed):
    features, regions, centres = descriptor_problem(seed)
    labels, margin = direct_assign(features, centres)
    assert margin > 1e-4
    out = vlad_per_region(features, regions, centres)
    assert out.shape == (len(regions), centres.size) and out.dtype == np.float32
    expected = direct_segvlad(features, regions, centres, labels)
    np.testing.assert_allclose(out, expected, rtol=0, atol=ATOL)
    np.testing.assert_array_equal(out[0], 0.0)
    np.testing.assert_allclose(np.linalg.norm(out[1:], axis=1), 1.0, rtol=0, atol=ATOL)


def test_segvlad_descriptors_with_given_labels_and_empty_clusters():
    features, regions, centres = descriptor_problem(7, k=6)
    labels = np.random.default_rng(0).integers(0, 4, len(features))  # clusters 4, 5 unused
    out = vlad_per_region(features, regions, centres, labels)
    np.testing.assert_allclose(
        out, direct_segvlad(features, regions, centres, labels), rtol=0, atol=ATOL
    )
    blocks = out.reshape(len(regions), 6, -1)
    np.testing.assert_array_equal(blocks[:, 4:], 0.0)


def test_whole_image_region_equals_anyloc_vlad():
    from vprflow.aggregation.vlad import vlad

    features, regions, centres = descriptor_problem(3)
    whole = vlad_per_region(features, regions[1:2], centres)[0]
    np.testing.assert_allclose(whole, vlad(features, centres), rtol=0, atol=ATOL)


# ------------------------------------------------------------ whole image


def direct_image_segvlad(features, masks, centres, image_size, patch, order, crop_aligned):
    h, w, d = features.shape
    membership = direct_membership(masks, image_size, (h, w), patch, crop_aligned)
    centroids = direct_centroids(masks)
    if len(masks) <= 3:
        adjacency = np.zeros((len(masks), len(masks)), dtype=bool)
        adjacency[:, : min(len(masks), 2)] = True
    else:
        adjacency = direct_delaunay_adjacency(centroids)
    reach = direct_power(adjacency, order)
    regions = np.zeros_like(membership)
    for s in range(len(masks)):
        for t in range(len(masks)):
            if reach[s, t]:
                regions[s] |= membership[t]
    flat = features.reshape(h * w, d)
    labels, margin = direct_assign(flat, centres)
    assert margin > 1e-4
    return direct_segvlad(flat, regions, centres, labels)


def clear_features(rng, n, centres, margin=1e-3):
    """Random unit descriptors, redrawn until none is near a tie between two centres."""
    features = unit_rows(rng.standard_normal((n, centres.shape[1])))
    unit = centres / np.linalg.norm(centres, axis=1, keepdims=True)
    while True:
        ordered = np.sort(features @ unit.T, axis=1)
        close = ordered[:, -1] - ordered[:, -2] < margin
        if not close.any():
            return features.astype(np.float32)
        features[close] = unit_rows(rng.standard_normal((close.sum(), centres.shape[1])))


def blob_masks(rng, n, height, width):
    """Rectangles at random places (non-empty, distinct centroids, overlaps allowed)."""
    masks = np.zeros((n, height, width), dtype=bool)
    for s in range(n):
        y, x = rng.integers(0, height - 2), rng.integers(0, width - 2)
        masks[s, y : y + rng.integers(1, 5), x : x + rng.integers(1, 6)] = True
    return masks


@pytest.mark.parametrize("order", [0, 1, 2, 3])
@pytest.mark.parametrize("crop_aligned", [False, True])
@pytest.mark.parametrize("n_masks", [2, 3, 12])
def test_image_segvlad_matches_composed_direct_pieces(order, crop_aligned, n_masks):
    rng = np.random.default_rng(100 + 10 * order + n_masks)
    patch, image_size, grid = 5, (33, 42), (6, 8)
    centres = rng.standard_normal((4, 10)).astype(np.float32)
    features = clear_features(rng, grid[0] * grid[1], centres).reshape(*grid, 10)
    masks = blob_masks(rng, n_masks, 16, 21)
    out = image_segvlad(features, masks, centres, image_size, patch, order, crop_aligned)
    expected = direct_image_segvlad(
        features, masks, centres, image_size, patch, order, crop_aligned
    )
    np.testing.assert_allclose(out, expected, rtol=0, atol=ATOL)


@pytest.mark.parametrize("crop_aligned", [False, True])
def test_image_without_masks_has_no_descriptors(crop_aligned):
    features = np.ones((4, 5, 6), np.float32)
    centres = np.eye(3, 6, dtype=np.float32)
    masks = np.zeros((0, 10, 12), dtype=bool)
    assert mask_patch_membership(masks, (28, 35), (4, 5), 7, crop_aligned).shape == (0, 20)
    for order in (0, 3):
        out = image_segvlad(features, masks, centres, (28, 35), 7, order, crop_aligned)
        assert out.shape == (0, 18)


# ------------------------------------------------------------ order 0 skips the graph


@pytest.mark.parametrize("small_graph", ["published", "complete"])
@pytest.mark.parametrize("crop_aligned", [False, True])
@pytest.mark.parametrize("n_masks", [0, 1, 2, 3, 4, 12, 30])
def test_order_0_without_the_graph_is_the_graph_paths_bits(n_masks, crop_aligned, small_graph):
    """Order 0 skips the graph (A^0 = I); the descriptors are exactly those of the graph
    path it replaced: centroids, adjacency (the small-graph quirk included, where a
    segment may lack its self loop), its 0th power, then (A^0 M) > 0."""
    rng = np.random.default_rng(500 + n_masks + 7 * crop_aligned)
    patch, image_size, grid = 5, (33, 42), (6, 8)
    centres = rng.standard_normal((4, 10)).astype(np.float32)
    features = clear_features(rng, grid[0] * grid[1], centres).reshape(*grid, 10)
    masks = blob_masks(rng, n_masks, 16, 21) if n_masks else np.zeros((0, 16, 21), bool)
    if n_masks >= 12:
        masks[5] = False  # an empty mask: a NaN centroid on the graph path
    out = image_segvlad(features, masks, centres, image_size, patch, 0, crop_aligned, small_graph)

    membership = mask_patch_membership(masks, image_size, grid, patch, crop_aligned)
    adjacency = segment_adjacency(segment_centroids(masks), small_graph)
    graph_regions = (neighbourhood(adjacency, 0).astype(np.float32) @ membership) > 0
    forced = vlad_per_region(features.reshape(-1, 10), graph_regions, centres)
    assert out.dtype == forced.dtype and out.shape == forced.shape == (n_masks, 40)
    np.testing.assert_array_equal(out, forced)  # bit for bit

    # The regions against the float64 formula: the 0th matrix power, whatever A holds.
    regions = segment_regions(masks, membership, 0, small_graph)
    power = np.linalg.matrix_power(adjacency.astype(np.float64), 0)
    np.testing.assert_array_equal(regions, (power @ membership.astype(np.float64)) > 0)
    np.testing.assert_array_equal(regions, graph_regions)


def test_order_0_never_builds_the_graph(monkeypatch):
    def no_graph(*args, **kwargs):
        raise AssertionError("order 0 built the segment graph")

    monkeypatch.setattr(segvlad, "segment_adjacency", no_graph)
    monkeypatch.setattr(segvlad, "segment_centroids", no_graph)
    rng = np.random.default_rng(3)
    centres = rng.standard_normal((4, 10)).astype(np.float32)
    features = clear_features(rng, 48, centres).reshape(6, 8, 10)
    masks = blob_masks(rng, 12, 16, 21)
    assert image_segvlad(features, masks, centres, (33, 42), 5, 0).shape == (12, 40)
    with pytest.raises(AssertionError, match="built the segment graph"):
        image_segvlad(features, masks, centres, (33, 42), 5, 1)


@pytest.mark.parametrize("order", [0, 2])
@pytest.mark.parametrize("n_masks", [2, 12])
def test_unknown_small_graph_fails_at_any_order_and_size(order, n_masks):
    rng = np.random.default_rng(order + n_masks)
    masks = blob_masks(rng, n_masks, 16, 21)
    features = np.ones((6, 8, 10), np.float32)
    centres = np.eye(4, 10, dtype=np.float32)
    with pytest.raises(ValueError, match="unknown small_graph 'nonsense'"):
        image_segvlad(features, masks, centres, (33, 42), 5, order, small_graph="nonsense")


# A descriptors job's imports, then one image at ORDER; prints whether scipy got loaded.
JOB_IMPORTS = textwrap.dedent(
    """
    import sys
    import numpy as np
    import vprflow.stages.jobs, vprflow.stages.runner, vprflow.stages.descriptors
    from vprflow.aggregation.segvlad import image_segvlad

    rng = np.random.default_rng(0)
    masks = np.zeros((12, 16, 21), bool)
    for s in range(12):
        y, x = rng.integers(0, 12), rng.integers(0, 17)
        masks[s, y : y + 4, x : x + 4] = True
    features = rng.standard_normal((6, 8, 10)).astype(np.float32)
    centres = rng.standard_normal((4, 10)).astype(np.float32)
    assert image_segvlad(features, masks, centres, (33, 42), 5, ORDER).shape == (12, 40)
    print("scipy" in sys.modules)
    """
)


@pytest.mark.parametrize(("order", "loads_scipy"), [(0, False), (1, True)])
def test_order_0_job_does_not_import_scipy(order, loads_scipy):
    """scipy (120-330 ms to import) is only for the graph, which order 0 does not build;
    order 1 shows that the check would see it."""
    code = JOB_IMPORTS.replace("ORDER", str(order))
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=False, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split()[-1] == str(loads_scipy)
