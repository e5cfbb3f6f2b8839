"""PCA against a float64 eigen-decomposition of the covariance written out here.

Data are float32 with well separated variances (eigen-gaps at least ~10% of the
eigenvalue), so components are well conditioned. Tolerances: explained variance rtol
1e-4; components (after matching signs) 1e-4 absolute (unit vectors); whitened
training projections have per-component variance 1 within 1e-3 and cross-covariance
below 1e-3; L2 norms 1 within 1e-5. Randomised PCA on rank-10 data plus 1e-3 noise vs
exact SVD: variance rtol 1e-5, components 1e-5 absolute.
"""

from __future__ import annotations

import numpy as np
import pytest

from vprflow.aggregation.pca import Pca, _randomized_pca, exact_pca_bytes, fit_pca


def anisotropic(n, d, seed=0):
    """Rows with per-axis scales 3.0 .. 0.3 in a random rotation, plus an offset."""
    rng = np.random.default_rng(seed)
    rotation = np.linalg.qr(rng.standard_normal((d, d)))[0]
    scales = np.geomspace(3.0, 0.3, d)
    x = (rng.standard_normal((n, d)) * scales) @ rotation.T + rng.normal(0, 5, d)
    return x.astype(np.float32)


def direct_pca(x, dim):
    """Covariance (n - 1 denominator) built with an explicit sum of outer products."""
    x = np.asarray(x, dtype=np.float64)
    n, d = x.shape
    mean = x.sum(axis=0) / n
    cov = np.zeros((d, d))
    for row in x:
        cov += np.outer(row - mean, row - mean)
    cov /= n - 1
    values, vectors = np.linalg.eigh(cov)
    order = np.argsort(values)[::-1][:dim]
    return mean, vectors[:, order].T, values[order]


def match_signs(components, reference):
    signs = np.sign(np.sum(components * reference, axis=1))
    assert (signs != 0).all()
    return components * signs[:, None]


@pytest.mark.parametrize(
    ("n", "d", "dim"),
    [
        (400, 12, 5),  # n > d: covariance path
        (400, 12, 12),
        (25, 60, 10),  # n < d: Gram-matrix path
        (25, 60, 24),  # all n - 1 non-trivial axes
    ],
)
def test_fit_pca_matches_covariance_eigendecomposition(n, d, dim):
    x = anisotropic(n, d, seed=n + d)
    pca = fit_pca(x, dim, whiten=False)
    mean, components, variance = direct_pca(x, dim)
    assert pca.components.shape == (dim, d) and pca.explained_variance.shape == (dim,)
    np.testing.assert_allclose(pca.mean, mean, rtol=0, atol=1e-4)
    np.testing.assert_allclose(pca.explained_variance, variance, rtol=1e-4)
    np.testing.assert_allclose(
        pca.components, match_signs(components, pca.components), rtol=0, atol=1e-4
    )
    # Deterministic sign: the largest-magnitude entry of each axis is positive.
    pivot = np.abs(pca.components).argmax(axis=1)
    assert (pca.components[np.arange(dim), pivot] > 0).all()


def test_dim_is_capped_at_n_minus_1_and_d():
    assert fit_pca(anisotropic(10, 40), 100).components.shape == (9, 40)
    assert fit_pca(anisotropic(50, 6), 100).components.shape == (6, 6)
    with pytest.raises(ValueError, match="at least 2"):
        fit_pca(anisotropic(1, 4), 2)


@pytest.mark.parametrize(("n", "d", "dim"), [(500, 10, 6), (30, 80, 12)])
def test_whitening_gives_unit_variance_on_training_data(n, d, dim):
    x = anisotropic(n, d, seed=3)
    pca = fit_pca(x, dim, whiten=True)
    y = pca.transform(x, normalize=False).astype(np.float64)
    assert y.shape == (n, dim)
    np.testing.assert_allclose(y.mean(axis=0), 0.0, rtol=0, atol=1e-3)
    cov = np.cov(y, rowvar=False)
    np.testing.assert_allclose(np.diag(cov), 1.0, rtol=0, atol=1e-3)
    np.testing.assert_allclose(cov - np.diag(np.diag(cov)), 0.0, rtol=0, atol=1e-3)
    # Without whitening the variances are the eigenvalues.
    plain = fit_pca(x, dim, whiten=False).transform(x, normalize=False).astype(np.float64)
    np.testing.assert_allclose(plain.var(axis=0, ddof=1), pca.explained_variance, rtol=1e-3)


def test_transform_is_direct_projection_then_l2_normalisation():
    x = anisotropic(200, 16, seed=4)
    queries = anisotropic(7, 16, seed=5)
    for whiten in (False, True):
        pca = fit_pca(x, 8, whiten=whiten)
        mean, components, variance = direct_pca(x, 8)
        components = match_signs(components, pca.components)
        expected = (queries.astype(np.float64) - mean) @ components.T
        if whiten:
            expected /= np.sqrt(variance)
        expected /= np.linalg.norm(expected, axis=1, keepdims=True)
        out = pca.transform(queries)
        assert out.dtype == np.float32
        np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, rtol=0, atol=1e-5)
        np.testing.assert_allclose(out, expected, rtol=0, atol=1e-4)


def test_transform_of_stored_arrays():
    pca = Pca(
        mean=np.array([1.0, 1.0], np.float32),
        components=np.array([[0.0, 1.0], [1.0, 0.0]], np.float32),
        explained_variance=np.array([4.0, 1.0], np.float32),
        whiten=True,
    )
    out = pca.transform(np.array([[3.0, 5.0]], np.float32), normalize=False)
    np.testing.assert_allclose(out, [[4.0 / 2.0, 2.0 / 1.0]])  # exact in float32
    # A float32 norm and division land within a few ulps (6e-8 each) of 2**-0.5, how many
    # depends on the BLAS: rtol 1e-6 (the default 1e-7 is about one ulp here).
    np.testing.assert_allclose(
        pca.transform(np.array([[3.0, 5.0]])), [[2**-0.5, 2**-0.5]], rtol=1e-6
    )


@pytest.mark.parametrize("dim", [5, 10])
def test_randomized_pca_matches_exact_svd_on_low_rank_data(dim):
    rng = np.random.default_rng(0)
    n, d, rank = 300, 200, 10
    u = np.linalg.qr(rng.standard_normal((n, rank)))[0]
    v = np.linalg.qr(rng.standard_normal((d, rank)))[0]
    x = (u * np.linspace(50, 10, rank)) @ v.T + 1e-3 * rng.standard_normal((n, d))
    centred = (x - x.mean(axis=0)).astype(np.float32)
    components, variance = _randomized_pca(centred, dim, seed=1)
    _, singular, vt = np.linalg.svd(centred.astype(np.float64), full_matrices=False)
    np.testing.assert_allclose(variance, singular[:dim] ** 2 / (n - 1), rtol=1e-5)
    np.testing.assert_allclose(match_signs(components, vt[:dim]), vt[:dim], rtol=0, atol=1e-5)


def test_randomized_pca_centres_implicitly():
    rng = np.random.default_rng(3)
    low_rank = rng.standard_normal((300, 6)) @ rng.standard_normal((6, 80))
    x = (low_rank + 5.0 + 1e-3 * rng.standard_normal((300, 80))).astype(np.float32)
    mean = x.mean(axis=0)
    implicit, var_implicit = _randomized_pca(x, 6, seed=1, mean=mean)
    explicit, var_explicit = _randomized_pca(x - mean, 6, seed=1)
    np.testing.assert_allclose(var_implicit, var_explicit, rtol=1e-4)
    np.testing.assert_allclose(np.abs(implicit @ explicit.T), np.eye(6), atol=1e-4)


# ------------------------------------------------- the exact solver at any size


def decaying(n, d, seed, power=1.0):
    """Rows with singular values decaying as a power law (like VLAD descriptors), in a
    random rotation, plus an offset; distinct singular values (gaps >= ~1%)."""
    rng = np.random.default_rng(seed)
    rank = min(n, d)
    u = np.linalg.qr(rng.standard_normal((n, rank)))[0]
    v = np.linalg.qr(rng.standard_normal((d, rank)))[0]
    singular = 100.0 * np.arange(1, rank + 1) ** -power
    return ((u * singular) @ v.T + rng.normal(0, 1, d)).astype(np.float32)


def svd_reference(x, dim):
    """float64 SVD of the centred data: axes [dim, D] and variances S^2 / (n - 1)."""
    x = np.asarray(x, dtype=np.float64)
    centred = x - x.mean(axis=0)
    _, singular, vt = np.linalg.svd(centred, full_matrices=False)
    return vt[:dim], singular[:dim] ** 2 / (len(x) - 1)


def max_principal_sine(components, axes):
    """Largest principal-angle sine between span(components) and span(axes) (rows):
    the spectral norm of the part of the (row-normalised) components outside the
    reference subspace. Computed directly, not as sqrt(1 - cos^2), which loses half
    the digits."""
    ours = np.asarray(components, np.float64)
    ours /= np.linalg.norm(ours, axis=1, keepdims=True)
    outside = ours - (ours @ axes.T) @ axes
    return float(np.linalg.norm(outside, ord=2))


def whitened_gram_on_probes(components, variance, probes):
    """``(P W^T)(P W^T)^T`` with ``W = components / sqrt(variance)``: the inner
    products whitened retrieval sees, on probe vectors (invariant to signs and to
    rotations inside equal-variance subspaces)."""
    projected = probes @ (np.asarray(components, np.float64).T / np.sqrt(variance))
    return projected @ projected.T


@pytest.mark.parametrize(
    ("n", "d", "dim"),
    [
        (600, 40, 30),  # covariance side
        (60, 500, 50),  # Gram side
        (300, 9000, 120),  # above the old 8192 switch to the randomised SVD: still exact
    ],
)
def test_exact_solver_matches_float64_svd(n, d, dim):
    """Tolerances: the input is float32 and the solver works in float64, so variances
    agree to rtol 1e-6; principal-angle sines below 1e-5 (gaps between consecutive
    singular values are >= 1%, so axes are well conditioned); the whitened Gram on 8
    probes within 1e-6 of its largest entry."""
    x = decaying(n, d, seed=n + d)
    pca = fit_pca(x, dim, whiten=True)
    axes, variance = svd_reference(x, dim)
    assert pca.dim == dim
    np.testing.assert_allclose(pca.explained_variance, variance, rtol=1e-6)
    assert max_principal_sine(pca.components, axes) < 1e-5
    # Axis by axis too (after matching signs), including the last one.
    np.testing.assert_allclose(match_signs(axes, pca.components), pca.components, atol=1e-5)
    probes = np.random.default_rng(0).standard_normal((8, d))
    ours = whitened_gram_on_probes(pca.components, pca.explained_variance, probes)
    reference = whitened_gram_on_probes(axes, variance, probes)
    np.testing.assert_allclose(ours, reference, rtol=0, atol=1e-6 * np.abs(reference).max())


@pytest.mark.parametrize(
    ("n", "d", "rank", "dim"),
    [
        (50, 200, 49, 100),  # 50 samples: at most 49 directions of variance
        (100, 40, 10, 30),  # samples in a 10-dimensional affine subspace
        (30, 900, 10, 1024),  # Gram side, rank 10, asked for far more
    ],
)
@pytest.mark.parametrize("solver", ["exact", "randomized"])
def test_dim_is_capped_at_the_numerical_rank(n, d, rank, dim, solver):
    rng = np.random.default_rng(rank)
    basis = np.linalg.qr(rng.standard_normal((d, rank)))[0].T  # [rank, D]
    x = (rng.standard_normal((n, rank)) * np.linspace(3, 1, rank)) @ basis + rng.normal(0, 4, d)
    pca = fit_pca(x.astype(np.float32), dim, whiten=True, solver=solver)
    assert pca.dim == min(rank, n - 1)
    assert np.isfinite(pca.components).all() and (pca.explained_variance > 0).all()
    y = pca.transform(x, normalize=False).astype(np.float64)
    assert np.isfinite(y).all()
    # Whitening of the kept axes is exact on the training data: unit variance each.
    np.testing.assert_allclose(y.var(axis=0, ddof=1), 1.0, rtol=1e-3)
    assert np.isfinite(pca.transform(rng.standard_normal((5, d)))).all()


def test_identical_samples_cannot_be_fitted():
    with pytest.raises(ValueError, match="all identical"):
        fit_pca(np.ones((5, 3), np.float32), 2)


def test_unknown_solver_is_named():
    with pytest.raises(ValueError, match="'arpack'"):
        fit_pca(anisotropic(20, 4), 2, solver="arpack")


def test_exact_memory_estimate_counts_the_smaller_square():
    # 17places shapes: 20,000 samples of 49,152 dims -> the 20,000^2 Gram matrix.
    assert exact_pca_bytes(20000, 49152, 1024) == 8 * (
        20000**2 + 2048 * 49152 + 20000 * 1024 + 1024 * 49152
    )
    assert exact_pca_bytes(49152, 20000, 1024) == exact_pca_bytes(20000, 49152, 1024) - 8 * (
        1024 * 49152 - 1024 * 20000
    )
