"""GeM / average / max pooling against direct per-channel loops in float64.

Tolerance: float32 results vs float64 loops, rtol 1e-5 and atol 1e-6 (values are O(1)).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from vprflow.aggregation.pooling import average_pool, gem, max_pool, segment_gem


def tokens(shape=(4, 5, 6), seed=0):
    return np.random.default_rng(seed).standard_normal(shape).astype(np.float32)


def columns(x):
    """Per-channel lists of token values, via explicit loops."""
    flat = np.asarray(x, dtype=np.float64).reshape(-1, x.shape[-1])
    return [[float(flat[i, d]) for i in range(flat.shape[0])] for d in range(flat.shape[1])]


def signed_root(value, p):
    return math.copysign(abs(value) ** (1.0 / p), value)


def direct_gem(x, p, eps, negatives):
    out = []
    for col in columns(x):
        if negatives == "signed":
            mean = sum(math.copysign(abs(v) ** p, v) for v in col) / len(col)
        elif negatives == "abs":
            mean = sum(abs(v) ** p for v in col) / len(col)
        else:
            mean = sum(max(v, eps) ** p for v in col) / len(col)
        out.append(signed_root(mean, p))
    return np.array(out)


def unit(v):
    return v / math.sqrt(sum(float(e) ** 2 for e in v))


def check(fast, slow):
    assert fast.dtype == np.float32 and fast.shape == slow.shape
    np.testing.assert_allclose(fast, slow, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("negatives", ["signed", "abs", "clamp"])
@pytest.mark.parametrize("p", [1.0, 2.0, 3.0, 4.5])
@pytest.mark.parametrize("shape", [(4, 5, 6), (9, 3)])
def test_gem_matches_direct(negatives, p, shape):
    x = tokens(shape, seed=int(p * 10))
    check(gem(x, p=p, negatives=negatives), direct_gem(x, p, 1e-6, negatives))
    check(
        gem(x, p=p, negatives=negatives, l2_normalize=True),
        unit(direct_gem(x, p, 1e-6, negatives)),
    )


def test_gem_signed_equals_published_mean_of_cubes():
    # Published (default flags): m = mean(x**3); sign(m) * |m|**(1/3).
    x = tokens((7, 4), seed=3).astype(np.float64)
    m = (x**3).mean(axis=0)
    check(gem(x), np.sign(m) * np.abs(m) ** (1 / 3))


def test_gem_p1_signed_is_mean_and_clamp_uses_eps():
    x = tokens((6, 5), seed=4)
    check(gem(x, p=1.0), x.astype(np.float64).mean(axis=0))
    negative = -np.ones((3, 2), dtype=np.float32)
    check(gem(negative, p=3.0, eps=1e-2, negatives="clamp"), np.full(2, 1e-2))


def test_gem_large_p_approaches_max_for_positive_tokens():
    x = np.abs(tokens((50, 8), seed=5)) + 0.1
    # Not rounding but the approximation: max * 50**(-1/200) <= GeM <= max, i.e. within 2%.
    np.testing.assert_allclose(gem(x, p=200.0), x.max(axis=0), rtol=0.03)


def test_average_and_max_match_direct():
    x = tokens((3, 4, 5), seed=6)
    avg = np.array([sum(col) / len(col) for col in columns(x)])
    mx = np.array([max(col) for col in columns(x)])
    check(average_pool(x), avg)
    check(max_pool(x), mx)
    check(average_pool(x, l2_normalize=True), unit(avg))
    check(max_pool(x, l2_normalize=True), unit(mx))


def test_flat_and_grid_inputs_agree():
    x = tokens((4, 5, 6), seed=8)
    flat = x.reshape(-1, 6)
    for pool in (gem, average_pool, max_pool):
        np.testing.assert_array_equal(pool(x), pool(flat))


def test_zero_vector_normalisation_is_safe():
    assert np.all(average_pool(np.zeros((3, 4)), l2_normalize=True) == 0)


@pytest.mark.parametrize("p", [0, -1.0, float("nan"), float("inf")])
def test_gem_rejects_bad_power(p):
    with pytest.raises(ValueError, match="p must be"):
        gem(tokens(), p=p)


def test_gem_rejects_unknown_negatives_mode():
    with pytest.raises(ValueError, match="relu"):
        gem(tokens(), negatives="relu")


@pytest.mark.parametrize("shape", [(5,), (2, 3, 4, 5), (0, 4)])
def test_pooling_rejects_bad_shapes(shape):
    for pool in (gem, average_pool, max_pool):
        with pytest.raises(ValueError):
            pool(np.zeros(shape, dtype=np.float32))


# ------------------------------------------------- as the descriptors stage runs them


def direct_channel_normalised(x):
    """Each channel divided by (its L2 norm over all tokens + 1e-10), float64 loops."""
    flat = np.asarray(x, dtype=np.float64).reshape(-1, x.shape[-1])
    out = flat.copy()
    for d in range(flat.shape[1]):
        out[:, d] /= math.sqrt(sum(v * v for v in flat[:, d])) + 1e-10
    return out


def features_store(tmp_path, grid: np.ndarray) -> str:
    """A features store holding one image's float32 grid ``[h, w, D]``."""
    from vprflow.core import stores

    path = str(tmp_path / "features.zarr")
    with stores.atomic_store(path, {"stage": "features"}) as group:
        stores.write_array(group, "features", grid[None].astype(np.float32))
    return path


def vocabulary_store(tmp_path, centres: np.ndarray) -> str:
    """A vocabulary store holding float32 ``centres [K, D]``."""
    from vprflow.core import stores

    path = str(tmp_path / "vocabulary.zarr")
    with stores.atomic_store(path, {"stage": "vocabulary"}) as group:
        stores.write_array(group, "centres", centres)
    return path


def describe_image(spec: dict, inputs: dict) -> np.ndarray:
    """Image 0's descriptor through the aggregator's entry, as the stages compute it."""
    from vprflow.aggregation.aggregators import aggregator
    from vprflow.stages.image_descriptors import image_descriptor

    return image_descriptor(aggregator(spec["aggregator"]), spec, inputs)(0)


@pytest.mark.parametrize("aggregator", ["gem", "average", "max"])
def test_stage_pools_channel_normalised_tokens_by_default(aggregator, tmp_path):
    """The SNSM authors' GeM / average / max baselines pool tokens normalised per
    channel over the image (``normalize_tensor``), not the stored features."""
    grid = (tokens((4, 5, 6), seed=3) * 7.0).astype(np.float32)
    inputs = {"features": features_store(tmp_path, grid)}
    spec = {"aggregator": aggregator, "p": 3.0, "normalization": "channel"}
    pooled = describe_image(spec, inputs)
    normalised = direct_channel_normalised(grid)
    expected = {
        "gem": lambda: direct_gem(normalised, 3.0, 1e-6, "signed"),
        "average": lambda: np.array([sum(c) / len(c) for c in columns(normalised)]),
        "max": lambda: np.array([max(c) for c in columns(normalised)]),
    }[aggregator]()
    np.testing.assert_allclose(pooled, expected, rtol=1e-5, atol=1e-6)
    raw = describe_image({**spec, "normalization": "none"}, inputs)
    assert not np.allclose(raw, pooled, rtol=1e-3)


def test_stage_vlad_normalises_each_patch_first(tmp_path):
    """AnyLoc's VLAD (``norm_descs=True``) L2-normalises every patch before assignment
    and residuals; float32 vs float64 loops, rtol 1e-4 / atol 1e-5."""
    from test_vlad import direct_vlad

    rng = np.random.default_rng(5)
    grid = (rng.standard_normal((3, 4, 8)) * rng.uniform(0.2, 5.0, (3, 4, 1))).astype(np.float32)
    centres = rng.standard_normal((3, 8)).astype(np.float32)
    path = vocabulary_store(tmp_path, centres)
    spec = {"aggregator": "anyloc_vlad", "normalize_descriptors": True}
    inputs = {"vocabulary": path, "features": features_store(tmp_path, grid)}
    vector = describe_image(spec, inputs)
    raw = describe_image({**spec, "normalize_descriptors": False}, inputs)
    flat = grid.reshape(-1, 8).astype(np.float64)
    unit = flat / np.linalg.norm(flat, axis=1, keepdims=True)
    np.testing.assert_allclose(vector, direct_vlad(unit, centres), rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(raw, direct_vlad(flat, centres), rtol=1e-4, atol=1e-5)


def test_segment_gem_is_gem_of_each_segments_tokens():
    rng = np.random.default_rng(11)
    tokens = rng.normal(size=(5, 7, 6))
    membership = rng.random((9, 35)) < 0.3
    membership[4] = False  # a segment covering no token
    got = segment_gem(tokens, membership, p=3.0)
    flat = tokens.reshape(35, 6)
    for s in range(9):
        rows = [flat[n] for n in range(35) if membership[s, n]]
        if not rows:
            np.testing.assert_array_equal(got[s], np.zeros(6))
            continue
        for d in range(6):  # direct float64 formula: sign(m) |m|^(1/p), m = mean x^3
            m = sum(float(r[d]) ** 3 for r in rows) / len(rows)
            want = math.copysign(abs(m) ** (1 / 3), m)
            assert abs(float(got[s, d]) - want) <= 1e-6 * max(1.0, abs(want)), (s, d)
    np.testing.assert_allclose(got[0], gem(flat[membership[0]], p=3.0), rtol=1e-6)


def test_segment_gem_rejects_a_membership_of_another_size():
    with pytest.raises(ValueError, match=r"membership must be \[S, 4\]"):
        segment_gem(np.zeros((4, 3)), np.ones((2, 5), bool))


def test_the_vlad_aggregator_is_anylocs_vlad_of_channel_normalised_tokens(tmp_path):
    """SNSM's `--vlad` baseline (aggregator ``vlad``): each channel divided by its L2
    norm over the image's tokens (+ 1e-10), then each patch L2-normalised, hard-assigned
    to the most cosine-similar centre, residuals summed, intra- and L2-normalised;
    float32 vs float64 loops, rtol 1e-4 / atol 1e-5."""
    from test_vlad import direct_vlad

    rng = np.random.default_rng(7)
    grid = (rng.standard_normal((3, 4, 8)) * rng.uniform(0.2, 5.0, (1, 1, 8))).astype(np.float32)
    centres = rng.standard_normal((3, 8)).astype(np.float32)
    path = vocabulary_store(tmp_path, centres)
    spec = {"aggregator": "vlad", "normalization": "channel", "normalize_descriptors": True}
    inputs = {"vocabulary": path, "features": features_store(tmp_path, grid)}
    vector = describe_image(spec, inputs)
    channel = direct_channel_normalised(grid)
    unit = channel / np.linalg.norm(channel, axis=1, keepdims=True)
    np.testing.assert_allclose(vector, direct_vlad(unit, centres), rtol=1e-4, atol=1e-5)
    flat = grid.reshape(-1, 8).astype(np.float64)
    per_patch = direct_vlad(flat / np.linalg.norm(flat, axis=1, keepdims=True), centres)
    assert not np.allclose(vector, per_patch, atol=1e-3)
