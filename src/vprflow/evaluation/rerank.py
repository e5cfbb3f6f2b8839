"""Training-free re-ranking of a query's top-K retrieved references by local matches
between dense patch features.

vprflow stores, per image, a ``[H_p, W_p]`` grid of patch descriptors ``[D]`` (L2-normalised
by default), read here flattened row-major: ``[P, D]`` with ``P = H_p * W_p``. Each
candidate reference gets a score (higher is better) and :func:`rerank` re-orders the
candidates by it. Both scores read the candidate's mutual nearest neighbour patch pairs
(:func:`candidate_pairs`), found once per (retrieval, features, ``top_k``) by the
``matches`` stage and scored by each re-ranker in its ``rerank`` stage. Two scores, named
by ``method`` (the ``kind`` of a ``rerankers`` entry, one :data:`RERANKERS` entry each,
at the end of this module: its score function over the pairs, options, defaults and
score kind):

``"mnn"``
    :func:`mnn_pair_scores` (:func:`mnn_score` per candidate): how many patch pairs are
    mutual nearest neighbours (or the sum of their similarities).
``"ransac"``
    :func:`ransac_pair_scores` (:func:`ransac_inliers` per candidate): how many of those
    mutual pairs, placed at their patch centres (:func:`patch_centres`), are inliers of
    one robustly fitted homography.

The ``rerank`` stage scores a query's stored pairs with :func:`pair_scorer`, the entry's
score function with its settings.

Published variants and how each function reproduces them
--------------------------------------------------------
Patch-NetVLAD (Hausler et al., CVPR 2021), QVPR/Patch-NetVLAD at commit
``39ab4e45725b1e7558dc9b108d31a7f3ce900614``:

* :func:`mutual_nearest_neighbours` is ``torch_nn`` plus the mutual check of
  ``PatchMatcher.compare_two_ransac`` in ``patchnetvlad/tools/patch_matcher.py``. That
  code turns the dot product into the distance ``sqrt(2 - 2 x.y + 1e-9)`` (a monotone
  decreasing map for unit vectors), takes the arg-min both ways (``torch.min`` /
  ``torch.argmin``: the first index on ties) and keeps database patch ``j`` when its
  nearest query patch's nearest database patch is ``j``. Here the arg-max of the dot
  product itself is taken: the same pairs for unit vectors, and well defined where the
  published ``sqrt`` is not (a float32 dot of two equal unit vectors can exceed 1, and
  ``2 - 2 x.y + 1e-9 < 0`` gives NaN) and for descriptors that are not unit length.
  Mutuality is symmetric, so iterating from the query side (here) or the database side
  (there) finds the same pairs; only their order differs (here: by query index).
* :func:`ransac_inliers` and the ``"ransac"`` score are ``compare_two_ransac`` (same file):
  ``cv2.findHomography(index_keypoints, query_keypoints, cv2.FM_RANSAC,
  ransacReprojThreshold=16 * stride * 1.5)`` over the mutual pairs' patch positions,
  scored by the inlier count (negated and divided by the patch count there, to mix
  patch sizes; one grid per store here, so the raw count ranks the same), with fewer than
  4 mutual pairs scoring 0. The fit runs the same way round (candidate -> query) and the
  default inlier threshold is the same 1.5 patches (``threshold`` of the ``rerankers``
  entry, in patches). The estimator differs; see :func:`ransac_inliers` for why.
* :func:`patch_centres` plays the part of ``calc_keypoint_centers_from_patches`` in
  ``patchnetvlad/models/local_matcher.py``: for 1x1 patches at stride 1 that is the
  VGG-16 receptive-field centre ``16 j + 7.5``, truncated to an integer; here the exact
  centre ``(j + 0.5) * patch`` of each ViT/DAISY patch, kept in float.

EffoVPR (Tzachor et al., ICLR 2025, arXiv:2405.18065), zero-shot re-ranking:

* :func:`mnn_score` with ``weighting="count"`` and ``min_similarity`` = the paper's T2 is
  its re-ranking score: the number of mutual nearest neighbour pairs between the query's
  and the candidate's local descriptors (the self-attention *values* of an intermediate
  DINOv2 layer) whose cosine similarity exceeds T2. The paper also keeps only patches
  whose CLS attention exceeds T1 before matching; vprflow stores no attention maps, so
  that selection is not reproduced (a caller may drop rows beforehand). Sources: the
  paper's abstract and the summary at sciencestack.ai/paper/2405.18065 ("mutual
  nearest-neighbor matching ... with fixed thresholds T1 and T2"); the method section and
  official code were not reachable here, so the exact rule was read from a third-party
  reproduction, PhamPhien-gif/EffoVPR at commit
  ``ab12041fe57803139f58f2699524419614fa832b``, ``src/effovpr/reranking/mnn.py``
  (count of mutual pairs with cosine ``> T2``, default 0.65) and ``keypoint_selection.py``
  (attention ``> T1``, default 0.05). ``min_similarity`` keeps pairs ``>=`` it (the
  ``rerankers`` schema's "at least this similar"), which differs from ``>`` only at exact
  equality. ``weighting="similarity"`` (the sum of the kept pairs' similarities) is a
  vprflow variant, not published.

Batched, and the same pairs
---------------------------
:func:`candidate_pairs` takes a query's K candidates in one float32 product ``[P, D] x
[D, K Q]`` (or a few, :func:`_product_elements` similarities each), not K products, and
reads every candidate's pairs off it by the ``argmax`` rule of
:func:`mutual_nearest_neighbours`. On CPUs that gives the same pairs and similarities as
:func:`mutual_nearest_neighbours` run per candidate, bit for bit: the batched product's
elements are the per-candidate product's bits, and numpy reads the pairs on the host
(:func:`_direct_pairs`). On other devices torch reads them on the device
(:func:`_device_pairs`) and only the pairs come back; the similarities are the batched
float32 product's (never TF32), which a library that picks its kernel by shape (cuBLAS,
split-K) may round otherwise than one product per candidate.
``benchmarks/bench_rerank.py`` times the batched scores against one product per candidate
and against the products alone.

Nothing here keeps state between calls; the RANSAC sampler is seeded per call. torch and
cv2 are named with ``lazy_import`` and imported when first used: the config schema lists
:data:`WEIGHTINGS` from here, and validating a config imports neither.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from vprflow.core.lazy import lazy_import

cv2 = lazy_import("cv2")
torch = lazy_import("torch")

WEIGHTINGS = ("count", "similarity")
MODELS = ("homography", "affine")

# A homography needs 4 correspondences; with exactly the minimal sample of any model
# every pair is trivially an inlier, so fewer than 4 score 0 for both models
# (Patch-NetVLAD: `len(mutuals) > 3`).
_MIN_CORRESPONDENCES = 4


def _as_matrix(x, name: str, device: torch.device | str | None = None) -> torch.Tensor:
    """``x`` as a 2-D floating tensor (numpy arrays are wrapped, not copied, on the CPU)."""
    t = torch.as_tensor(x)
    if t.ndim != 2:
        raise ValueError(f"{name} must be [N, D] patch descriptors, got shape {tuple(t.shape)}")
    if not t.is_floating_point():
        raise ValueError(f"{name} must be floating point (float32 expected), got {t.dtype}")
    return t if device is None else t.to(device)


def mutual_nearest_neighbours(
    query: torch.Tensor, candidate: torch.Tensor
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mutual nearest neighbour pairs between two sets of patch descriptors.

    ``query`` ``[P, D]``, ``candidate`` ``[Q, D]``: floating point (float32 expected),
    tensors on any torch device or numpy arrays; ``candidate`` is moved to ``query``'s
    device. Similarity is the dot product of the given descriptors (the cosine for
    L2-normalised ones). Pair ``(i, j)`` is kept when ``j`` is ``i``'s most similar
    candidate patch and ``i`` is ``j``'s most similar query patch. Ties go to the lower
    index, both ways (``torch.argmax`` documents that it returns the first maximal
    index).

    Returns ``(i [M] int64, j [M] int64, similarity [M] float32)`` as CPU numpy arrays,
    ordered by increasing ``i``; each ``i`` and each ``j`` occurs at most once.
    """
    q = _as_matrix(query, "query")
    c = _as_matrix(candidate, "candidate", q.device)
    if c.shape[1] != q.shape[1]:
        raise ValueError(f"candidate has descriptors of dimension {c.shape[1]}, query {q.shape[1]}")
    if q.shape[0] == 0 or c.shape[0] == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty.copy(), np.zeros(0, dtype=np.float32)
    dtype = torch.promote_types(q.dtype, c.dtype)
    similarity = q.to(dtype) @ c.to(dtype).T
    # argmax is documented to return the first maximal index on every device: that is
    # the lower-index tie rule, with no extra pass over the [P, Q] matrix.
    forward = similarity.argmax(dim=1)
    backward = similarity.argmax(dim=0)
    rows = torch.arange(q.shape[0], device=q.device)
    i = rows[backward[forward] == rows]
    j = forward[i]
    values = similarity[i, j]
    return (
        i.cpu().numpy().astype(np.int64),
        j.cpu().numpy().astype(np.int64),
        values.float().cpu().numpy(),
    )


def _is_integer(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def _check_min_similarity(min_similarity: float | None) -> None:
    if min_similarity is None:
        return
    if not isinstance(min_similarity, (int, float, np.number)) or isinstance(min_similarity, bool):
        raise ValueError(f"min_similarity must be a number or None, got {min_similarity!r}")
    if math.isnan(min_similarity):
        raise ValueError("min_similarity must be a number or None, got NaN")


def _kept(similarity: np.ndarray, min_similarity: float | None) -> np.ndarray:
    """Mask ``[M]`` of the pairs at least ``min_similarity`` similar (all when None)."""
    if min_similarity is None:
        return np.ones(len(similarity), dtype=bool)
    return similarity >= min_similarity


def _check_weighting(weighting: str) -> None:
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting must be one of {list(WEIGHTINGS)}, got {weighting!r}")


def mnn_score(
    query: torch.Tensor,
    candidate: torch.Tensor,
    weighting: str = "count",
    min_similarity: float | None = None,
) -> float:
    """Mutual-nearest-neighbour score of a candidate for a query (higher is better).

    ``query`` ``[P, D]``, ``candidate`` ``[Q, D]`` as in
    :func:`mutual_nearest_neighbours`. Only pairs with similarity ``>= min_similarity``
    count (all pairs when ``None``; EffoVPR's T2, see the module docstring).
    ``weighting``: ``"count"`` = the number of kept pairs (EffoVPR's score);
    ``"similarity"`` = the sum of their similarities (float64).
    """
    _check_weighting(weighting)
    _check_min_similarity(min_similarity)
    _, _, similarity = mutual_nearest_neighbours(query, candidate)
    kept = similarity[_kept(similarity, min_similarity)]
    if weighting == "count":
        return float(len(kept))
    return float(kept.astype(np.float64).sum())


def patch_centres(grid_h: int, grid_w: int, patch: int) -> np.ndarray:
    """Pixel centres ``[grid_h * grid_w, 2]`` float64 of a patch grid, as ``(x, y)`` in
    row-major patch order (the order of the flattened features).

    Coordinates are those of the feature image (the centre-cropped image the backbone
    saw), with pixel ``(0, 0)`` covering ``[0, 1) x [0, 1)``: patch ``(r, c)`` covers
    ``[c * patch, (c + 1) * patch)`` horizontally, so its centre is
    ``((c + 0.5) * patch, (r + 0.5) * patch)``. (OpenCV puts pixel centres at integers,
    0.5 lower; the same shift of both images leaves the inliers of a homography or an
    affine fit unchanged.)
    """
    for name, value in (("grid_h", grid_h), ("grid_w", grid_w), ("patch", patch)):
        if not _is_integer(value) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    rows, cols = np.meshgrid(np.arange(grid_h), np.arange(grid_w), indexing="ij")
    centres = np.stack([cols.ravel(), rows.ravel()], axis=1).astype(np.float64)
    return (centres + 0.5) * patch


def _check_ransac_options(
    threshold: float, model: str, seed: int, max_iters: int, confidence: float
) -> None:
    if not threshold > 0:
        raise ValueError(f"threshold must be > 0, got {threshold!r}")
    if model not in MODELS:
        raise ValueError(f"model must be one of {list(MODELS)}, got {model!r}")
    if not _is_integer(seed) or not 0 <= seed < 2**31:
        raise ValueError(f"seed must be an integer in [0, 2**31), got {seed!r}")
    if not _is_integer(max_iters) or max_iters < 1:
        raise ValueError(f"max_iters must be a positive integer, got {max_iters!r}")
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}")


def _points(xy, name: str) -> np.ndarray:
    points = np.asarray(xy, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2:
        raise ValueError(f"{name} must be [M, 2] (x, y) points, got shape {points.shape}")
    return points


def ransac_inliers(
    query_xy: np.ndarray,
    candidate_xy: np.ndarray,
    threshold: float,
    model: str = "homography",
    seed: int = 0,
    max_iters: int = 2000,
    confidence: float = 0.999,
) -> int:
    """Inliers of a robust fit mapping ``candidate_xy`` ``[M, 2]`` onto ``query_xy``
    ``[M, 2]`` (row ``m`` of each is one correspondence, in pixels).

    ``model``: ``"homography"`` (``cv2.findHomography``) or ``"affine"``
    (``cv2.estimateAffine2D``). The score is the number of correspondences whose
    reprojection error ``|| model(candidate_xy) - query_xy ||`` under the fitted model is
    ``<= threshold`` pixels: Patch-NetVLAD's RANSAC inlier rule, counted here by this
    function rather than read from OpenCV's mask so that it means the same for every
    estimator setting. Fewer than 4 correspondences, or no model found (e.g. all points
    collinear), give 0. Needs OpenCV (``opencv-python-headless``, a vprflow dependency).

    Estimator: MAGSAC++ (``cv2.SCORE_METHOD_MAGSAC`` with its sigma-consensus local
    optimisation, uniform sampling, no final polishing, single-threaded) through
    ``cv2.UsacParams``, where Patch-NetVLAD calls ``cv2.findHomography`` with
    ``cv2.FM_RANSAC`` (== ``cv2.RANSAC``). Why:

    * Seeding. ``cv2.RANSAC`` draws its samples from a local RNG with a fixed state
      (``RNG rng((uint64)-1)`` in OpenCV's ``ptsetreg.cpp``), so it is deterministic but
      ignores any seed; the ``cv2.USAC_*`` flags run with a fixed state too, and
      ``cv2.setRNGSeed`` changes neither (checked on opencv-python-headless 5.0.0). Only
      ``UsacParams.randomGeneratorState`` makes ``seed`` act: the same seed gives the
      same count, and the result does not depend on OpenCV's global RNG.
    * Stability. A score that moves with the seed reorders candidates at random. On four
      synthetic sets of 250 correspondences (50 homography inliers with 1.2 px noise,
      threshold 3 px, 2000 iterations, confidence 0.999), USAC with RANSAC scoring (with
      or without local optimisation) gave counts with a standard deviation of 7-15 over
      20 seeds, collapsing to 5-16 inliers on some seeds; this MAGSAC++ setting stayed
      within 3 of the true count on every seed (standard deviation at most 0.44), and
      ``cv2.RANSAC`` (its one fixed seed) fell 2-4 short. With 30% inliers or more all
      of them agree with the truth.
    """
    _check_ransac_options(threshold, model, seed, max_iters, confidence)
    query_points = _points(query_xy, "query_xy")
    candidate_points = _points(candidate_xy, "candidate_xy")
    if len(candidate_points) != len(query_points):
        raise ValueError(
            f"candidate_xy has {len(candidate_points)} points, query_xy {len(query_points)}"
        )
    if len(query_points) < _MIN_CORRESPONDENCES:
        return 0
    params = cv2.UsacParams()
    params.threshold = float(threshold)
    params.confidence = float(confidence)
    params.maxIterations = int(max_iters)
    params.randomGeneratorState = int(seed)
    params.sampler = cv2.SAMPLING_UNIFORM
    params.score = cv2.SCORE_METHOD_MAGSAC
    params.loMethod = cv2.LOCAL_OPTIM_SIGMA
    # Final polishing (LSQ, MAGSAC or covariance) changed no count on those synthetic
    # sets, so the count is taken from the model the sigma-consensus step settles on.
    params.final_polisher = cv2.NONE_POLISHER
    # Parallel USAC's result depends on thread timing; one thread keeps `seed` decisive.
    params.isParallel = False
    src = np.ascontiguousarray(candidate_points, dtype=np.float32)
    dst = np.ascontiguousarray(query_points, dtype=np.float32)
    if model == "homography":
        fitted, _ = cv2.findHomography(src, dst, params)
    else:
        fitted, _ = cv2.estimateAffine2D(src, dst, params=params)
    if fitted is None or fitted.size == 0:
        return 0
    matrix = np.eye(3)
    matrix[: fitted.shape[0]] = fitted
    mapped = np.c_[candidate_points, np.ones(len(candidate_points))] @ matrix.T
    with np.errstate(divide="ignore", invalid="ignore"):
        # A point mapped to infinity (w = 0) gets an inf or NaN error: not an inlier.
        projected = mapped[:, :2] / mapped[:, 2:]
        error = np.linalg.norm(projected - query_points, axis=1)
    return int(np.count_nonzero(error <= threshold))


# Elements of one batched product [P, k * Q] on the CPU: about 64 MiB in float32, so the
# G/14 grid at 322 px (529 patches) takes 59 candidates a product, DAISY's 300-patch grid
# all 100 of a K = 100 query.
_PRODUCT_ELEMENTS = 1 << 24

# On other devices a product of up to 1 GiB (float32), a quarter of the free memory at
# most: the G/14 grid of a 640 x 480 image (34 x 45 = 1,530 patches) takes a K = 100
# query's candidates in one product, which keeps the device busy where 100 did not.
_DEVICE_PRODUCT_ELEMENTS = 1 << 28


def _host_argmax(device: torch.device) -> bool:
    """Whether the pairs are read off the product by numpy on the host (CPUs: the product
    is there already, and numpy's argmax over this layout is 2-6x torch's) rather than by
    torch on the product's device (elsewhere: only the pairs come back)."""
    return device.type == "cpu"


def _product_elements(device: torch.device) -> int:
    """Similarities a product on ``device`` holds at most (see the constants above)."""
    if _host_argmax(device):
        return _PRODUCT_ELEMENTS
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        return max(_PRODUCT_ELEMENTS, min(_DEVICE_PRODUCT_ELEMENTS, free // 16))
    return _DEVICE_PRODUCT_ELEMENTS


# Candidates per argmax task in _direct_pairs: numpy's argmax over axis 0 copies its input
# with the axis moved last, and a block of 4 candidates keeps that copy in cache (DAISY's
# 300 x 100 x 300: 15.2 ms whole, 12.7 in blocks of 4 on one thread, 8.0 on two).
_ARGMAX_BLOCK = 4


def _direct_pairs(
    similarity: np.ndarray, threads: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(forward [k, P] int64, mutual [k, P] bool, values [k, P] float32)`` of a CPU
    float32 product ``similarity [P, k, Q]``: each query patch's most similar patch of
    each candidate, whether that pair is mutual, and its similarity.

    numpy's ``argmax`` keeps :func:`mutual_nearest_neighbours`' rule (the first maximal
    index; NaN counts as the maximum in both) and runs 2-6x faster than torch's over this
    layout, where the two ``argmax`` passes cost as much as the product itself. They run
    by blocks of :data:`_ARGMAX_BLOCK` candidates on ``threads`` threads (numpy releases
    the GIL); a candidate's argmax does not depend on the blocks."""
    n_p, n_k = similarity.shape[:2]

    def block(start: int) -> tuple[np.ndarray, np.ndarray]:
        part = similarity[:, start : start + _ARGMAX_BLOCK]
        return part.argmax(axis=2), part.argmax(axis=0)  # [P, b], [b, Q]

    starts = range(0, n_k, _ARGMAX_BLOCK)
    if threads > 1 and len(starts) > 1:
        with ThreadPoolExecutor(min(threads, len(starts))) as pool:
            parts = list(pool.map(block, starts))
    else:
        parts = [block(start) for start in starts]
    forward = np.concatenate([f for f, _ in parts], axis=1)  # [P, k]
    backward = np.concatenate([b for _, b in parts], axis=0)  # [k, Q]
    mutual = backward[np.arange(n_k), forward] == np.arange(n_p)[:, None]
    values = np.take_along_axis(similarity, forward[:, :, None], axis=2)[:, :, 0]
    return forward.T.astype(np.int64), np.ascontiguousarray(mutual.T), values.T.copy()


def _device_pairs(similarity: torch.Tensor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_direct_pairs` of a product ``similarity [P, k, Q]`` on any device, by
    torch's ``argmax`` there (the rule of :func:`mutual_nearest_neighbours`, which takes
    the same ``argmax``): only the ``[k, P]`` results come back to the host."""
    n_p = similarity.shape[0]
    forward = similarity.argmax(dim=2)  # [P, k]
    backward = similarity.argmax(dim=0)  # [k, Q]
    rows = torch.arange(n_p, device=similarity.device)
    mutual = backward.gather(1, forward.T) == rows  # [k, P]
    values = similarity.gather(2, forward[:, :, None])[:, :, 0]  # [P, k]
    return (
        forward.T.cpu().numpy().astype(np.int64),
        mutual.cpu().numpy(),
        values.T.float().cpu().numpy(),
    )


def _split(forward: np.ndarray, mutual: np.ndarray, values: np.ndarray) -> list:
    """Each candidate's ``(i, j, similarity)`` from ``[k, P]`` arrays: its mutual query
    patches ``i`` (increasing), their ``forward`` patches and ``values``."""
    k, i = np.nonzero(mutual)  # row-major: by candidate, then increasing i
    ends = np.cumsum(np.count_nonzero(mutual, axis=1))[:-1]
    return list(
        zip(
            np.split(i, ends),
            np.split(forward[k, i], ends),
            np.split(values[k, i], ends),
            strict=True,
        )
    )


def candidate_pairs(query, candidates) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Each candidate's mutual nearest neighbour pairs with ``query`` ``[P, D]``, exactly as
    :func:`mutual_nearest_neighbours` finds them one candidate at a time:
    ``[(i [M] int64, j [M] int64, similarity [M] float32)]`` per candidate of
    ``candidates`` ``[K, Q, D]`` (moved to ``query``'s device), ``i`` increasing.

    What the ``matches`` stage stores, and what the re-rankers' pair scorers
    (:func:`pair_scorer`) read: no threshold is applied (``min_similarity`` and
    ``weighting`` act when scoring), so the pairs depend on the features alone.

    The candidates take one product ``[P, D] x [D, k Q]`` per group of ``k`` (up to
    :func:`_product_elements` similarities), in the dtype
    :func:`mutual_nearest_neighbours` takes (float32 for float32 features, never TF32),
    and each pair keeps that product's similarity. On CPUs the batched product's elements
    are the per-candidate product's bits (``tests/evaluation/test_rerank.py`` checks it at the
    benchmark's grids), and numpy reads the pairs off it (:func:`_direct_pairs`); on other
    devices torch reads them there (:func:`_device_pairs`), by the same ``argmax``, and a
    library such as cuBLAS, which picks its kernel by shape, may round a batched product's
    elements otherwise than a per-candidate one (``benchmarks/check_gpu.py`` counts the
    pairs and similarities that differ). Other dtypes on a CPU take one product per
    candidate.
    """
    q = _as_matrix(query, "query")
    stack = torch.as_tensor(candidates)
    if stack.ndim != 3 or not stack.is_floating_point():
        raise ValueError(
            "candidates must be [K, Q, D] floating-point patch descriptors, got shape "
            f"{tuple(stack.shape)} of {stack.dtype}"
        )
    if stack.shape[2] != q.shape[1]:
        raise ValueError(
            f"candidates have descriptors of dimension {stack.shape[2]}, query {q.shape[1]}"
        )
    n_k, n_q = stack.shape[:2]
    n_p, dim = q.shape
    on_host = _host_argmax(q.device)
    float32 = q.dtype == torch.float32 and stack.dtype == torch.float32
    if n_p == 0 or n_q == 0 or dim == 0 or (on_host and not float32):
        return [mutual_nearest_neighbours(q, stack[k]) for k in range(n_k)]
    dtype = torch.promote_types(q.dtype, stack.dtype)
    q = q.to(dtype)
    per_product = max(1, _product_elements(q.device) // (n_p * n_q))
    found: list = []
    precision = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision("highest")  # float32 products, never TF32
    try:
        for start in range(0, n_k, per_product):
            group = stack[start : start + per_product].to(q.device, dtype)
            similarity = (q @ group.reshape(-1, dim).T).view(n_p, len(group), n_q)
            if on_host:
                # The product's thread budget (run_stage sets torch's to the rule's).
                parts = _direct_pairs(similarity.numpy(), torch.get_num_threads())
            else:
                parts = _device_pairs(similarity)
            del similarity
            found.extend(_split(*parts))
    finally:
        torch.set_float32_matmul_precision(precision)
    return found


def _with_kept(pairs, min_similarity) -> list:
    """``pairs`` (:func:`candidate_pairs`' tuples) with the mask ``[M]`` of those kept by
    ``min_similarity``."""
    found = []
    for k, (i, j, similarity) in enumerate(pairs):
        similarity = np.asarray(similarity)
        if similarity.dtype != np.float32 or not len(i) == len(j) == len(similarity):
            raise ValueError(
                f"pairs[{k}] must be (i [M], j [M], similarity [M] float32), got lengths "
                f"{len(i)}, {len(j)}, {len(similarity)} and similarity dtype {similarity.dtype}"
            )
        found.append((i, j, similarity, _kept(similarity, min_similarity)))
    return found


def pair_scorer(
    method: str, options: dict, grid: tuple[int, int], patch: int
) -> Callable[[list], np.ndarray]:
    """What the ``rerank`` stage scores each query's candidates with: ``pairs``
    (:func:`candidate_pairs`' list, or a ``matches`` store's) -> scores ``[K]`` float64
    (higher is better).

    ``method`` names a :data:`RERANKERS` entry, whose pair scorer
    (:func:`mnn_pair_scores`, :func:`ransac_pair_scores`) gets ``options`` (the keys of a
    ``rerankers`` entry) over the entry's defaults and its fixed settings, and the patch
    centres of the features' ``grid = (h, w)`` of ``patch``-pixel patches. Every setting
    is checked here, before any candidate: a bad value is a ``ValueError``, an option the
    method does not take a ``TypeError``, each naming it.
    """
    try:
        entry = reranker(method)
    except ValueError as error:
        raise ValueError(f"method: {error}") from None
    settings = entry.settings(options)
    centres = patch_centres(*grid, patch)
    score = entry.scores
    score([], centres, patch, **settings)
    return functools.partial(score, centres=centres, patch=patch, **settings)


def _mnn(found: list, weighting: str) -> np.ndarray:
    scores = np.zeros(len(found), dtype=np.float64)
    for k, (_, _, similarity, kept) in enumerate(found):
        if weighting == "count":
            scores[k] = float(np.count_nonzero(kept))
        else:
            # As mnn_score: the kept float32 values (in increasing i), widened, summed by numpy.
            scores[k] = float(similarity[kept].astype(np.float64).sum())
    return scores


def mnn_pair_scores(
    pairs, centres: np.ndarray, patch: int, *, weighting: str, min_similarity
) -> np.ndarray:
    """The ``"mnn"`` re-ranker's score function: :func:`mnn_score` of each candidate from
    its mutual pairs ``pairs`` (:func:`candidate_pairs`' list, or a ``matches`` store's),
    float64 ``[K]`` (``centres`` and ``patch`` unused)."""
    _check_weighting(weighting)
    _check_min_similarity(min_similarity)
    return _mnn(_with_kept(pairs, min_similarity), weighting)


def _ransac_options(min_similarity, threshold, model, seed, max_iters, confidence) -> dict:
    """The estimator's options for :func:`ransac_inliers`, after checking every ransac
    setting: before any fit, so a bad one fails even when no candidate reaches it."""
    _check_min_similarity(min_similarity)
    ransac = {"model": model, "seed": seed, "max_iters": max_iters, "confidence": confidence}
    _check_ransac_options(threshold, **ransac)
    return ransac


def _ransac(found: list, centres: np.ndarray, pixels: float, ransac: dict) -> np.ndarray:
    scores = np.zeros(len(found), dtype=np.float64)
    for k, (i, j, _, kept) in enumerate(found):
        scores[k] = ransac_inliers(centres[i[kept]], centres[j[kept]], pixels, **ransac)
    return scores


def ransac_pair_scores(
    pairs,
    centres: np.ndarray,
    patch: int,
    *,
    min_similarity,
    threshold: float,
    seed: int,
    model: str,
    max_iters: int,
    confidence: float,
) -> np.ndarray:
    """The ``"ransac"`` re-ranker's score function: :func:`ransac_inliers` over each
    candidate's mutual pairs ``pairs`` (:func:`candidate_pairs`' list, or a ``matches``
    store's) kept by ``min_similarity``, placed at their ``centres``
    (:func:`patch_centres`); ``threshold`` is in patches (``threshold * patch`` pixels).
    Float64 ``[K]``."""
    ransac = _ransac_options(min_similarity, threshold, model, seed, max_iters, confidence)
    found = _with_kept(pairs, min_similarity)
    return _ransac(found, centres, float(threshold) * patch, ransac)


def rerank(ranking_row: np.ndarray, scores: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Re-order one query's first ``K`` candidates by decreasing score; the rest of the
    retrieval follows them in its own order.

    ``ranking_row`` ``[D]`` int64: reference indices in retrieval order, ``-1`` = no
    candidate; ``scores`` ``[K]`` float64, ``K <= D``, aligned with its first ``K``
    entries (the re-ranked top K). The sort is stable, so equal scores keep their
    retrieval order; entries ``K..D-1`` (not re-ranked) come next in retrieval order,
    scored as the lowest re-ranked score (0 when none), so scores never rise down the
    ranking; every ``-1`` entry goes last (in its original order, a re-ranked one with
    its score), whatever its score. A re-ranker that looked at fewer candidates than
    the table's deepest Recall@N thus leaves Recall@N for ``N >= K`` as the retrieval's,
    instead of truncating the ranking. Returns ``(new_ranking [D] int64, new_scores [D]
    float64)``.
    """
    ranking = np.asarray(ranking_row)
    values = np.asarray(scores, dtype=np.float64)
    if ranking.ndim != 1:
        raise ValueError(f"ranking_row must be [D], got shape {ranking.shape}")
    if values.ndim != 1 or len(values) > len(ranking):
        raise ValueError(
            f"scores must be [K] with K <= {len(ranking)} (ranking_row's length), "
            f"got shape {values.shape}"
        )
    if not np.issubdtype(ranking.dtype, np.integer):
        raise ValueError(f"ranking_row must hold integer reference indices, got {ranking.dtype}")
    if np.any(ranking < -1):
        raise ValueError("ranking_row holds indices below -1 (-1 alone marks no candidate)")
    k = len(values)
    present = np.flatnonzero(ranking[:k] >= 0)
    if np.isnan(values[present]).any():
        raise ValueError("scores are NaN for some candidates; cannot order them")
    # Negating keeps the stable sort's tie order (retrieval order) for a decreasing sort.
    head = present[np.argsort(-values[present], kind="stable")]
    tail = k + np.flatnonzero(ranking[k:] >= 0)
    order = np.concatenate([head, tail, np.flatnonzero(ranking < 0)]).astype(np.int64)
    floor = float(values[present].min()) if len(present) else 0.0
    full = np.concatenate([values, np.full(len(ranking) - k, floor)])
    return ranking[order].astype(np.int64), full[order]


@dataclass(frozen=True)
class Reranker:
    """A ``rerankers.<name>.kind``: how it scores a query's candidates.

    ``scores``: its score function, ``(pairs, centres [P, 2], patch, **settings) ->
    scores [K] float64`` (higher is better), ``pairs`` one ``(i [M], j [M], similarity
    [M] float32)`` per candidate: its mutual nearest neighbour patch pairs with the
    query, as :func:`candidate_pairs` finds them and the ``matches`` stage stores them
    (:func:`pair_scorer` binds it for the ``rerank`` stage; an empty ``pairs`` checks the
    settings alone).
    ``defaults``: the entry's keys that shape its scores, with their defaults
    (``load_schema`` writes them into the schema, so the config's defaults are these);
    the rest of the entry, ``features`` and ``top_k``, reach the key through the plan.
    ``fixed``: the function's further settings, which the config leaves at these values
    (not in the key: only a code change moves them). ``score``: the kind of score stored
    (a :data:`vprflow.evaluation.precision_recall.SCORE_KINDS` name). ``description``:
    what it scores, in the config's words (the schema's ``kind`` description lists every
    kind's).
    """

    name: str
    scores: Callable[..., np.ndarray]
    defaults: dict
    fixed: dict = field(default_factory=dict)
    score: str = "matches"
    description: str = field(kw_only=True)

    @property
    def options(self) -> tuple[str, ...]:
        """The config keys the kind reads besides ``kind``, ``features`` and ``top_k``."""
        return tuple(self.defaults)

    def settings(self, options: dict) -> dict:
        """Every setting of the score function: ``options`` over the defaults; a key
        the kind does not take is refused by name."""
        known = {**self.defaults, **self.fixed}
        unknown = sorted(set(options) - set(known))
        if unknown:
            raise TypeError(
                f"re-ranker {self.name!r} got unknown options {unknown}; it takes {list(known)}"
            )
        return {**known, **options}


RERANKERS: dict[str, Reranker] = {
    r.name: r
    for r in (
        # EffoVPR's zero-shot score: the count of mutual pairs at least T2 similar.
        Reranker(
            "mnn",
            mnn_pair_scores,
            {"weighting": "count", "min_similarity": None},
            description="count mutual nearest neighbours between the query's and each "
            "candidate's patch features",
        ),
        # Patch-NetVLAD's RANSAC score; threshold in patches (1.5, as published). The
        # estimator's budget stays fixed: the config never set it.
        Reranker(
            "ransac",
            ransac_pair_scores,
            {"min_similarity": None, "threshold": 1.5, "seed": 0},
            fixed={"model": "homography", "max_iters": 2000, "confidence": 0.999},
            description="inliers of a homography fitted to those mutual nearest neighbour matches",
        ),
    )
}


def reranker(name: str) -> Reranker:
    if name not in RERANKERS:
        raise ValueError(f"unknown re-ranker kind {name!r}; expected one of {sorted(RERANKERS)}")
    return RERANKERS[name]
