"""AnyLoc VLAD (REFERENCE.md section 1, step 4) against direct float64 loops.

Tolerances: ``vlad`` works in float32 and is compared with a float64 loop over points
and clusters at 1e-5 absolute (entries of a unit vector). Assignments are compared
exactly; the random data are checked to have a clear winning centre per point (a
best-minus-second dot-product margin above 1e-4) so float32 rounding cannot flip one.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from vprflow.aggregation.vlad import assign, fit_spherical_kmeans, vlad

ATOL = 1e-5


def unit_rows(x):
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def random_problem(n=120, k=6, d=10, seed=0):
    rng = np.random.default_rng(seed)
    x = unit_rows(rng.standard_normal((n, d))).astype(np.float32)
    # Un-normalised centres of different lengths: residuals must use them as they are.
    centres = (rng.standard_normal((k, d)) * rng.uniform(0.5, 2.0, (k, 1))).astype(np.float32)
    return x, centres


def direct_assign(x, centres):
    """argmax_c x . C_c / |C_c|, one point and one centre at a time, in float64."""
    labels, margins = [], []
    for point in np.asarray(x, dtype=np.float64):
        scores = []
        for centre in np.asarray(centres, dtype=np.float64):
            norm = math.sqrt(sum(v * v for v in centre))
            scores.append(sum(a * b for a, b in zip(point, centre, strict=True)) / norm)
        best = max(range(len(scores)), key=lambda c: (scores[c], -c))
        labels.append(best)
        ordered = sorted(scores, reverse=True)
        margins.append(ordered[0] - ordered[1] if len(ordered) > 1 else np.inf)
    return np.array(labels), np.array(margins)


def direct_vlad(x, centres, labels=None):
    """Residuals to un-normalised centres, per-cluster sums, intra-norm, flatten, L2."""
    x = np.asarray(x, dtype=np.float64)
    centres = np.asarray(centres, dtype=np.float64)
    if labels is None:
        labels, _ = direct_assign(x, centres)
    k, d = centres.shape
    blocks = []
    for c in range(k):
        total = np.zeros(d)
        for point, label in zip(x, labels, strict=True):
            if label == c:
                total += point - centres[c]
        norm = math.sqrt(float(total @ total))
        blocks.append(total / norm if norm > 0 else total)
    flat = np.concatenate(blocks)
    norm = math.sqrt(float(flat @ flat))
    return flat / norm if norm > 0 else flat


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_assign_matches_direct_argmax(seed):
    x, centres = random_problem(seed=seed)
    expected, margins = direct_assign(x, centres)
    assert margins.min() > 1e-4  # the comparison below is not decided by rounding
    labels = assign(x, centres)
    assert labels.dtype == np.int64
    np.testing.assert_array_equal(labels, expected)


def test_assign_uses_normalised_centres():
    # The long centre would win a raw dot product; after normalisation the short one does.
    centres = np.array([[10.0, 10.0], [0.0, 0.1]], dtype=np.float32)
    x = np.array([[0.1, 0.99]], dtype=np.float32)
    assert (x @ centres.T).argmax() == 0
    np.testing.assert_array_equal(assign(x, centres), [1])
    assert assign(np.zeros((0, 2), np.float32), centres).shape == (0,)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_vlad_matches_direct_loops(seed):
    x, centres = random_problem(seed=seed)
    _, margins = direct_assign(x, centres)
    assert margins.min() > 1e-4
    out = vlad(x, centres)
    assert out.shape == (centres.size,)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, direct_vlad(x, centres), rtol=0, atol=ATOL)
    assert abs(np.linalg.norm(out) - 1.0) < ATOL


def test_vlad_with_given_labels_matches_direct():
    x, centres = random_problem(n=50, seed=5)
    labels = np.random.default_rng(9).integers(0, len(centres), len(x))
    np.testing.assert_allclose(
        vlad(x, centres, labels), direct_vlad(x, centres, labels), rtol=0, atol=ATOL
    )


def test_vlad_residuals_use_unnormalised_centres():
    x, centres = random_problem(seed=4)
    # Scaling every centre leaves the assignment unchanged but not the residuals.
    a, b = vlad(x, centres), vlad(x, 3.0 * centres)
    assert np.abs(a - b).max() > 1e-2
    np.testing.assert_allclose(b, direct_vlad(x, 3.0 * centres), rtol=0, atol=ATOL)


def test_empty_clusters_stay_zero():
    rng = np.random.default_rng(3)
    d = 8
    x = unit_rows(np.abs(rng.standard_normal((40, d)))).astype(np.float32)  # positive orthant
    centres = unit_rows(rng.standard_normal((5, d))).astype(np.float32)
    centres[1] = -np.ones(d) / math.sqrt(d)  # points the opposite way: never chosen
    centres[3] = -np.ones(d) / math.sqrt(d) * 2.0
    labels = assign(x, centres)
    assert not np.isin([1, 3], labels).any()
    out = vlad(x, centres).reshape(len(centres), d)
    np.testing.assert_array_equal(out[[1, 3]], 0.0)
    used = sorted(set(labels.tolist()))
    # Every non-empty block is intra-normalised: equal norms 1 / sqrt(#non-empty).
    np.testing.assert_allclose(
        np.linalg.norm(out[used], axis=1), 1 / math.sqrt(len(used)), rtol=0, atol=ATOL
    )
    np.testing.assert_allclose(out.ravel(), direct_vlad(x, centres), rtol=0, atol=ATOL)


def test_vlad_of_no_descriptors_is_zero():
    _, centres = random_problem(seed=0)
    out = vlad(np.zeros((0, centres.shape[1]), np.float32), centres)
    np.testing.assert_array_equal(out, np.zeros(centres.size))


# ------------------------------------------------------------------- k-means


def clustered(seed=0, k=4, d=16, per_cluster=100, noise=0.2):
    """Points around ``k`` orthonormal directions (pairwise cosine 0 between clusters)."""
    rng = np.random.default_rng(seed)
    directions = np.linalg.qr(rng.standard_normal((d, k)))[0].T
    labels = np.repeat(np.arange(k), per_cluster)
    x = unit_rows(directions[labels] + noise * rng.standard_normal((len(labels), d)))
    return x.astype(np.float32), directions, labels


@pytest.mark.parametrize("centres", ["unit", "mean"])
def test_kmeans_centres_are_deterministic_and_scale_free(centres):
    x, _, _ = clustered(seed=1, k=5)
    # Not normalised on input: fit_spherical_kmeans normalises itself.
    scaled = x * np.random.default_rng(0).uniform(0.5, 3.0, (len(x), 1)).astype(np.float32)
    a = fit_spherical_kmeans(scaled, n_clusters=5, n_iter=20, seed=7, centres=centres)
    b = fit_spherical_kmeans(scaled, n_clusters=5, n_iter=20, seed=7, centres=centres)
    assert a.shape == (5, x.shape[1]) and a.dtype == np.float32
    np.testing.assert_array_equal(a, b)
    norms = np.linalg.norm(a, axis=1)
    if centres == "unit":
        np.testing.assert_allclose(norms, 1.0, rtol=0, atol=1e-6)
    else:
        # Means of unit vectors spread around a direction are shorter than 1.
        assert (norms < 0.999).all() and (norms > 0.5).all()
    # The input scale does not matter (spherical k-means sees directions only).
    np.testing.assert_allclose(
        fit_spherical_kmeans(x, n_clusters=5, n_iter=20, seed=7, centres=centres),
        a,
        rtol=0,
        atol=1e-5,
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mean_centres_are_the_plain_means_of_their_members(seed):
    """AnyLoc's cosine k-means: a centre is the mean of the unit descriptors assigned to
    it by cosine, not re-normalised. Checked against float64 means of the members under
    the returned centres' own assignment (a converged k-means is its own fixed point),
    tolerance 1e-5 (float32 centres of unit vectors)."""
    x, directions, _ = clustered(seed=seed, noise=0.6)
    scaled = x * np.random.default_rng(seed).uniform(0.5, 3.0, (len(x), 1)).astype(np.float32)
    centres = fit_spherical_kmeans(scaled, n_clusters=len(directions), seed=seed, centres="mean")
    unit = fit_spherical_kmeans(scaled, n_clusters=len(directions), seed=seed, centres="unit")
    x64 = x.astype(np.float64)
    x64 /= np.linalg.norm(x64, axis=1, keepdims=True)
    normalised = centres / np.linalg.norm(centres, axis=1, keepdims=True)
    labels = np.argmax(x64 @ normalised.T, axis=1)
    for c in range(len(centres)):
        np.testing.assert_allclose(centres[c], x64[labels == c].mean(axis=0), rtol=0, atol=1e-5)
    # Same directions as the unit centres; norms well below 1 at this spread.
    np.testing.assert_allclose(normalised, unit, rtol=0, atol=1e-5)
    assert np.linalg.norm(centres, axis=1).max() < 0.95


def test_vlad_with_mean_centres_differs_from_unit_centres():
    """The residuals see the centre norms: VLAD with the plain-mean vocabulary is not
    VLAD with the normalised one (why the published default matters)."""
    x, directions, _ = clustered(seed=4, noise=0.6)
    mean = fit_spherical_kmeans(x, n_clusters=len(directions), seed=0, centres="mean")
    unit = fit_spherical_kmeans(x, n_clusters=len(directions), seed=0, centres="unit")
    a, b = vlad(x[:50], mean), vlad(x[:50], unit)
    np.testing.assert_allclose(a, direct_vlad(x[:50], mean), rtol=1e-4, atol=1e-5)
    assert float(a @ b) < 0.99


def test_kmeans_rejects_an_unknown_centres_mode():
    x, _, _ = clustered(seed=1, k=5)
    with pytest.raises(ValueError, match="'median'"):
        fit_spherical_kmeans(x, n_clusters=5, centres="median")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_kmeans_recovers_separated_clusters(seed):
    # k-means from a random initialisation can stop in a local minimum; with this
    # noise level faiss escapes it for these (fixed, hence deterministic) seeds.
    x, directions, truth = clustered(seed=seed)
    centres = fit_spherical_kmeans(x, n_clusters=len(directions), seed=seed, centres="unit")
    cosine = centres @ directions.T
    match = cosine.argmax(axis=1)
    assert sorted(match.tolist()) == list(range(len(directions)))  # one centre per cluster
    assert cosine.max(axis=1).min() > 0.99
    # A converged spherical k-means is a fixed point: every centre is the normalised
    # mean of the points assigned to it.
    labels = assign(x, centres)
    for c in range(len(centres)):
        mean = x[labels == c].astype(np.float64).mean(axis=0)
        np.testing.assert_allclose(centres[c], mean / np.linalg.norm(mean), rtol=0, atol=1e-5)
    # The clusters overlap a little at this noise level: allow 1% of points astray.
    assert np.mean(match[labels] == truth) > 0.99


def test_kmeans_needs_enough_points():
    x, _, _ = clustered(per_cluster=2, k=4)
    with pytest.raises(ValueError, match="at least 32"):
        fit_spherical_kmeans(x, n_clusters=32)
