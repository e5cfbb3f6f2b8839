"""Test vectors and the float64 check shared by the k-NN tests (tests/search/).

Tie rule: float32 distances may order two items differently from float64 (or from faiss)
only when their distances are within float32 rounding. Index sets are therefore compared
exactly on rows whose float64 gap between the k-th and (k+1)-th distance exceeds
:data:`GAP` (float32 errors here are below 1e-6); distances are compared to float64
within :data:`DIST_TOL`.
"""

from __future__ import annotations

import numpy as np

GAP = 1e-4
DIST_TOL = 1e-5


def unit_vectors(rng, n, d):
    x = rng.standard_normal((n, d))
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def clustered(rng, n, d, centres):
    """Unit vectors around ``centres [c, d]``, noise comparable to the centres' spacing."""
    labels = rng.integers(0, len(centres), n)
    x = centres[labels] + 0.5 * rng.standard_normal((n, d)) / np.sqrt(d)
    return (x / np.linalg.norm(x, axis=1, keepdims=True)).astype(np.float32)


def brute_force(database, queries):
    """All squared L2 distances in float64 ``[Nq, Nd]`` (differences, no expansion)."""
    diff = queries.astype(np.float64)[:, None, :] - database.astype(np.float64)[None, :, :]
    return (diff * diff).sum(-1)


def check_against_float64(distances, indices, database, queries, k):
    """Shapes and dtypes, distances vs float64, index sets on rows with a clear k-th gap."""
    exact = brute_force(database, queries)
    k_out = min(k, len(database))
    assert distances.shape == indices.shape == (len(queries), k_out)
    assert distances.dtype == np.float32 and indices.dtype == np.int64
    assert np.all(np.diff(distances, axis=1) >= 0)
    assert np.all((indices >= 0) & (indices < len(database)))
    assert all(len(set(row)) == k_out for row in indices)
    # Each returned distance is that of its index, and the sorted k smallest are float64's.
    np.testing.assert_allclose(
        distances, np.take_along_axis(exact, indices, 1), rtol=0, atol=DIST_TOL
    )
    ordered = np.sort(exact, axis=1)
    np.testing.assert_allclose(distances, ordered[:, :k_out], rtol=0, atol=DIST_TOL)
    if k_out < len(database):
        clear = ordered[:, k_out] - ordered[:, k_out - 1] > GAP
    else:
        clear = np.ones(len(queries), dtype=bool)
    assert clear.mean() > 0.5  # the comparison below is not vacuous
    truth = np.argsort(exact, axis=1, kind="stable")[:, :k_out]
    for row in np.flatnonzero(clear):
        assert set(indices[row]) == set(truth[row]), row
    return clear
