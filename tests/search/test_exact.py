"""Exact k-NN in torch against float64 brute force and faiss flat (tie rule and
tolerances: tests/knn_helpers.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from knn_helpers import DIST_TOL, GAP, brute_force, check_against_float64, clustered, unit_vectors

from vprflow.search import exact as knn_exact
from vprflow.search.exact import exact_knn
from vprflow.search.flat import flat_knn
from vprflow.search.topk import topk_agreement


@pytest.mark.parametrize("candidate_dtype", ["bfloat16", "float32"])
@pytest.mark.parametrize(
    ("n_db", "n_q", "dim", "k", "block_queries", "block_database"),
    [
        (300, 40, 32, 10, 4096, 65536),  # one block each
        (257, 33, 64, 20, 8, 50),  # ragged blocks on both sides: merging across blocks
        (37, 9, 16, 50, 4, 10),  # Nd < k: everything, sorted
        (200, 21, 24, 5, 21, 7),  # database blocks smaller than k + margin
    ],
)
def test_exact_knn_matches_float64(
    candidate_dtype, n_db, n_q, dim, k, block_queries, block_database
):
    rng = np.random.default_rng(n_db + dim)
    database, queries = unit_vectors(rng, n_db, dim), unit_vectors(rng, n_q, dim)
    distances, indices = exact_knn(
        database,
        queries,
        k,
        device="cpu",
        block_queries=block_queries,
        block_database=block_database,
        candidate_dtype=candidate_dtype,
    )
    check_against_float64(distances, indices, database, queries, k)


def test_exact_knn_float16_and_unnormalised_data():
    """float16 candidates with norms from 1e-3 to 1e3 (scaled blocks, no overflow)."""
    rng = np.random.default_rng(3)
    database = unit_vectors(rng, 150, 48) * rng.uniform(0.5, 2.0, (150, 1)).astype(np.float32)
    database[:5] *= np.float32(1e3)
    database[5:10] *= np.float32(1e-3)
    queries = unit_vectors(rng, 20, 48)
    for candidate_dtype in ("float16", "bfloat16"):
        distances, indices = exact_knn(
            database, queries, 15, device="cpu", block_database=64, candidate_dtype=candidate_dtype
        )
        check_against_float64(distances, indices, database, queries, 15)


@pytest.mark.parametrize("candidate_dtype", ["bfloat16", "float32"])
def test_widening_without_margin_is_still_exact(candidate_dtype):
    """margin=0 leaves rows uncertified: they must be widened, and the result stays exact."""
    rng = np.random.default_rng(5)
    centres = unit_vectors(rng, 6, 64)
    database, queries = clustered(rng, 400, 64, centres), clustered(rng, 30, 64, centres)
    stats = {}
    distances, indices = exact_knn(
        database,
        queries,
        12,
        device="cpu",
        block_database=150,
        candidate_dtype=candidate_dtype,
        margin=0,
        stats=stats,
    )
    assert stats["widened"] > 0
    check_against_float64(distances, indices, database, queries, 12)


def test_duplicates_tie_to_the_lowest_index():
    """More exact duplicates than k + margin: ties are exact and go to the lower index."""
    rng = np.random.default_rng(7)
    others = unit_vectors(rng, 100, 32)
    target = unit_vectors(rng, 1, 32)
    database = np.concatenate([others[:40], np.repeat(target, 90, axis=0), others[40:]])
    queries = np.concatenate([target, unit_vectors(rng, 3, 32)])
    stats = {}
    distances, indices = exact_knn(database, queries, 20, device="cpu", margin=5, stats=stats)
    assert stats["widened"] > 0
    np.testing.assert_array_equal(distances[0], np.zeros(20, np.float32))
    np.testing.assert_array_equal(indices[0], np.arange(40, 60))


@pytest.mark.parametrize("candidate_dtype", ["bfloat16", "float16", "float32"])
def test_certified_error_bound_holds(candidate_dtype):
    """The bound behind the candidate cut-off, checked pair by pair on this machine's GEMM:
    |d' - d| <= bound + 2 u |s~| for unit, heavy-tailed and unnormalised vectors."""
    rng = np.random.default_rng(31)
    heavy = rng.standard_normal((260, 48)) ** 5  # a few large coordinates: C-S nearly tight
    scaled = rng.standard_normal((260, 40)) * rng.uniform(0.01, 100, (260, 1))
    low = knn_exact.CANDIDATE_DTYPES[candidate_dtype]
    for data in (
        unit_vectors(rng, 260, 256),
        heavy / np.linalg.norm(heavy, axis=1)[:, None],
        scaled,
    ):
        data = torch.from_numpy(data.astype(np.float32))
        ref, query = knn_exact._side(data[:200], low), knn_exact._side(data[200:], low)
        raw, factor, unit = knn_exact._product(query, ref)
        product = raw.float() * factor  # s~
        approx = query.sq_norm[:, None] + ref.sq_norm[None, :] - 2 * product
        exact = ((data[200:, None, :] - data[None, :200, :]) ** 2).sum(-1)
        bound = knn_exact._error_bound(query, ref)[:, None] + 2 * unit / (1 - unit) * product.abs()
        assert torch.all((approx - exact).abs() <= bound)


def test_exact_knn_matches_faiss_flat():
    rng = np.random.default_rng(11)
    database, queries = unit_vectors(rng, 1500, 128), unit_vectors(rng, 120, 128)
    ours_d, ours_i = exact_knn(database, queries, 50, device="cpu", block_database=600)
    ref_d, ref_i = flat_knn(database, queries, 50)
    np.testing.assert_allclose(ours_d, ref_d, rtol=0, atol=DIST_TOL)
    exact = np.sort(brute_force(database, queries), axis=1)
    clear = exact[:, 50] - exact[:, 49] > GAP
    assert clear.mean() > 0.5
    for row in np.flatnonzero(clear):
        assert set(ours_i[row]) == set(ref_i[row]), row
    assert topk_agreement(ours_i, ref_i) > 0.99


def test_candidate_dtypes_agree():
    rng = np.random.default_rng(13)
    database, queries = unit_vectors(rng, 500, 96), unit_vectors(rng, 40, 96)
    d16, i16 = exact_knn(database, queries, 25, device="cpu", candidate_dtype="bfloat16")
    d32, i32 = exact_knn(database, queries, 25, device="cpu", candidate_dtype="float32")
    np.testing.assert_allclose(d16, d32, rtol=0, atol=1e-6)
    assert topk_agreement(i16, i32) > 0.99


def test_exact_knn_edge_cases_and_errors():
    rng = np.random.default_rng(17)
    database, queries = unit_vectors(rng, 20, 8), unit_vectors(rng, 3, 8)
    d, i = exact_knn(database, queries[:0], 5, device="cpu")
    assert d.shape == i.shape == (0, 5)
    d, i = exact_knn(database, queries, 0, device="cpu")
    assert d.shape == i.shape == (3, 0)
    with pytest.raises(ValueError, match="candidate_dtype"):
        exact_knn(database, queries, 5, candidate_dtype="int8")
    with pytest.raises(ValueError, match="dimension"):
        exact_knn(database, queries[:, :4], 5)
    bad = database.copy()
    bad[3, 2] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        exact_knn(bad, queries, 5, device="cpu")
    if not torch.cuda.is_available():
        with pytest.raises(RuntimeError, match="CUDA"):
            exact_knn(database, queries, 5, device="cuda")


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16, torch.float32])
def test_group_max_bounds_every_group(dtype):
    """Bit-pattern group maxima: the largest value where it is positive, else zero."""
    rng = np.random.default_rng(37)
    values = torch.from_numpy(rng.standard_normal((6, 40, 8)).astype(np.float32))
    values[0, :3] = -values[0, :3].abs()  # all negative
    values[1, 3] = 0.0
    values[1, 4] = -0.0
    values[1, 5] = torch.tensor([-0.0, 0.0, -1.0, -3.0, -0.0, -2.0, -5.0, -0.5])
    values = values.to(dtype)
    peak = knn_exact._group_max(values, -1)
    assert peak.dtype == dtype
    expected = values.float().amax(-1).clamp(min=0)
    assert torch.equal(peak.float(), expected)


@pytest.mark.parametrize("candidate_dtype", ["bfloat16", "float32"])
def test_select_leaves_out_only_keys_above_threshold(candidate_dtype):
    """_select by column groups (with a partial last group): distinct candidates, and every
    item left out has a key of at least the threshold, for unit and unnormalised rows (the
    latter reordered by norm, as exact_knn does)."""
    rng = np.random.default_rng(41)
    low = knn_exact.CANDIDATE_DTYPES[candidate_dtype]
    scaled = unit_vectors(rng, 1203, 24) * rng.uniform(0.2, 3.0, (1203, 1)).astype(np.float32)
    for ref_data in (unit_vectors(rng, 1203, 24), scaled):
        ref = knn_exact._by_norm(knn_exact._side(torch.from_numpy(ref_data), low))
        assert (ref.order is None) == (ref_data is not scaled)
        col_sq = ref.sq_norm if ref.order is None else ref.sq_norm[ref.order]
        query = knn_exact._side(torch.from_numpy(unit_vectors(rng, 30, 24)), low)
        raw, factor, _ = knn_exact._product(query, ref)
        key = knn_exact._keys(raw.clone(), factor, col_sq)
        kept = raw.clone()
        cand, _, threshold, full = knn_exact._select(raw, factor, col_sq, 9)
        assert full is None  # the grouped path: 1203 // 16 groups >= 4 * 9
        assert torch.equal(raw, kept)  # widening passes key rows of raw later
        assert all(len(set(row.tolist())) == 9 for row in cand)
        left_out = torch.ones_like(key, dtype=torch.bool).scatter_(1, cand, False)
        assert torch.all(torch.where(left_out, key, torch.inf) >= threshold[:, None])
        # Not vacuous: the threshold is about the 9th smallest key, as a full top-k's is.
        # Unit rows: up to the float32 spread of |r|^2 within a group; unnormalised ones
        # lose a little more (a group's smallest |r|^2 with its largest product).
        ninth = key.kthvalue(9, dim=1).values
        assert torch.all(threshold >= ninth - (0.05 if ref.order is not None else 1e-6))


@pytest.mark.parametrize("candidate_dtype", ["bfloat16", "float32"])
@pytest.mark.parametrize("margin", [0, 4])
def test_grouped_selection_is_exact(monkeypatch, candidate_dtype, margin):
    """Blocks wide enough for selection by column groups (small groups here): exact against
    float64 on clustered, unnormalised data with ragged blocks, widening included."""
    calls = []
    group_max = knn_exact._group_max
    monkeypatch.setattr(knn_exact, "GROUP", 3)
    monkeypatch.setattr(
        knn_exact, "_group_max", lambda g, d: calls.append(g.shape) or group_max(g, d)
    )
    rng = np.random.default_rng(43)
    centres = unit_vectors(rng, 5, 40)
    database = clustered(rng, 700, 40, centres) * rng.uniform(0.5, 2, (700, 1)).astype(np.float32)
    queries = clustered(rng, 50, 40, centres)
    stats = {}
    distances, indices = exact_knn(
        database,
        queries,
        8,
        device="cpu",
        block_queries=32,
        block_database=400,
        candidate_dtype=candidate_dtype,
        margin=margin,
        stats=stats,
    )
    assert calls  # the grouped path ran
    if margin == 0:
        assert stats["widened"] > 0
    check_against_float64(distances, indices, database, queries, 8)


def test_grouped_selection_duplicates_tie_to_the_lowest_index(monkeypatch):
    monkeypatch.setattr(knn_exact, "GROUP", 2)
    rng = np.random.default_rng(47)
    others = unit_vectors(rng, 300, 16)
    target = unit_vectors(rng, 1, 16)
    database = np.concatenate([others[:100], np.repeat(target, 30, axis=0), others[100:]])
    queries = np.concatenate([target, unit_vectors(rng, 3, 16)])
    distances, indices = exact_knn(database, queries, 12, device="cpu", margin=3)
    np.testing.assert_array_equal(distances[0], np.zeros(12, np.float32))
    np.testing.assert_array_equal(indices[0], np.arange(100, 112))
    check_against_float64(distances[1:], indices[1:], database, queries[1:], 12)


def test_second_step_rescores_only_rows_that_need_it():
    """Candidates beyond k + margin / 2 are re-scored only for rows whose certificate needs
    them: here some rows take them, most do not, none is widened, and the result is exact."""
    rng = np.random.default_rng(53)
    centres = unit_vectors(rng, 6, 64)
    database, queries = clustered(rng, 600, 64, centres), clustered(rng, 60, 64, centres)
    k, margin, block = 12, 16, 300
    stats = {}
    distances, indices = exact_knn(
        database, queries, k, device="cpu", block_database=block, margin=margin, stats=stats
    )
    passes = len(queries) * len(database) // block
    assert stats["widened"] == 0
    assert passes * (k + margin // 2) < stats["rescored"] < passes * (k + margin)
    check_against_float64(distances, indices, database, queries, k)


def _whole_block_side(x, low):
    """_side's values computed over the whole block at once (the unchunked formulas)."""
    sq_norm = torch.linalg.vecdot(x, x)
    scale = 1.0
    if low == torch.float16:
        scale = 2.0 ** -np.frexp(float(x.abs().max()))[1]
    rounded = (x * scale).to(low)
    hi = rounded.float() / scale
    return scale, rounded, sq_norm, torch.linalg.vector_norm(hi, dim=1), (hi - x).norm(dim=1)


@pytest.mark.parametrize("candidate_dtype", ["bfloat16", "float16"])
@pytest.mark.parametrize("rows", [1, 7, 64, 65, 200])
def test_side_by_chunks_equals_whole_block(monkeypatch, candidate_dtype, rows):
    """Chunked residual norms: bit for bit the whole-block values, chunks of one row, a
    ragged last chunk, exactly the block, and more than the block."""
    rng = np.random.default_rng(59)
    low = knn_exact.CANDIDATE_DTYPES[candidate_dtype]
    data = unit_vectors(rng, 65, 48) * rng.uniform(0.01, 50, (65, 1)).astype(np.float32)
    x = torch.from_numpy(data)
    monkeypatch.setattr(knn_exact, "_side_elements", lambda device: rows * 48)
    side = knn_exact._side(x, low)
    scale, rounded, sq_norm, hi_norm, lo_norm = _whole_block_side(x, low)
    assert side.scale == scale
    assert torch.equal(side.low, rounded)
    assert torch.equal(side.sq_norm, sq_norm)
    assert torch.equal(side.norm, sq_norm.sqrt())
    assert torch.equal(side.hi_norm, hi_norm)
    assert torch.equal(side.lo_norm, lo_norm)


@pytest.mark.parametrize(
    ("budget_rows", "budget_cols"), [(1, 1), (1, 5), (3, 17), (4, 17), (50, 17)]
)
def test_rescore_by_chunks_equals_one_pass(monkeypatch, budget_rows, budget_cols):
    """Chunked re-scoring (partial rows, columns split when a row's candidates exceed the
    budget): bit for bit the float32 ((q - r) ** 2).sum() of one whole gather."""
    rng = np.random.default_rng(61)
    ref = torch.from_numpy(unit_vectors(rng, 90, 40))
    query = torch.from_numpy(unit_vectors(rng, 10, 40))
    cand = torch.sort(torch.from_numpy(rng.integers(0, 90, (10, 17))), dim=1).values
    monkeypatch.setattr(
        knn_exact, "_rescore_elements", lambda device: budget_rows * budget_cols * 40
    )
    expected = ((ref[cand] - query[:, None, :]) ** 2).sum(-1)
    assert torch.equal(knn_exact._rescore(query, ref, cand), expected)


@pytest.mark.parametrize(
    ("n_db", "k", "block_database"),
    [
        (65, 10, 64),  # one row over a block: a one-row block
        (129, 10, 64),  # one row over two blocks
        (128, 10, 64),  # exactly two blocks
        (100, 40, 16),  # k larger than a block: every block merged whole
        (16, 40, 16),  # k larger than the whole database
    ],
)
def test_block_boundaries_with_small_chunks(monkeypatch, n_db, k, block_database):
    """Database sizes at and just over a block, k beyond a block, with chunks small enough
    to be ragged in _side and _rescore: exact against float64, and the same bits as with
    the default chunk sizes."""
    rng = np.random.default_rng(n_db + k)
    database, queries = unit_vectors(rng, n_db, 32), unit_vectors(rng, 23, 32)
    options = dict(device="cpu", block_queries=10, block_database=block_database)
    default = exact_knn(database, queries, k, **options)
    monkeypatch.setattr(knn_exact, "_side_elements", lambda device: 5 * 32)
    monkeypatch.setattr(knn_exact, "_rescore_elements", lambda device: 3 * 7 * 32)
    distances, indices = exact_knn(database, queries, k, **options)
    np.testing.assert_array_equal(distances, default[0])
    np.testing.assert_array_equal(indices, default[1])
    check_against_float64(distances, indices, database, queries, k)


def test_ties_across_block_and_chunk_boundaries(monkeypatch):
    """Exact duplicates straddling two database blocks and several _side / _rescore chunks:
    equal distances, ties to the lowest index."""
    monkeypatch.setattr(knn_exact, "_side_elements", lambda device: 3 * 24)
    monkeypatch.setattr(knn_exact, "_rescore_elements", lambda device: 2 * 5 * 24)
    rng = np.random.default_rng(67)
    others = unit_vectors(rng, 120, 24)
    target = unit_vectors(rng, 1, 24)
    database = np.concatenate([others[:55], np.repeat(target, 20, axis=0), others[55:]])
    queries = np.concatenate([target, unit_vectors(rng, 4, 24)])
    for candidate_dtype in ("bfloat16", "float16", "float32"):
        distances, indices = exact_knn(
            database,
            queries,
            15,
            device="cpu",
            block_database=64,
            candidate_dtype=candidate_dtype,
            margin=2,
        )
        np.testing.assert_array_equal(distances[0], np.zeros(15, np.float32))
        np.testing.assert_array_equal(indices[0], np.arange(55, 70))
        check_against_float64(distances[1:], indices[1:], database, queries[1:], 15)


@pytest.mark.parametrize("data", ["random", "clustered"])
def test_later_blocks_take_fewer_candidates_and_stay_exact(data):
    """Database blocks after the first start from the running k-th distances: nine rows in
    ten need fewer than k + margin / 2 candidates there, the others take the rest; the
    result stays exact and ties go to the lower index across blocks."""
    rng = np.random.default_rng(71)
    if data == "random":
        database, queries = unit_vectors(rng, 1200, 48), unit_vectors(rng, 80, 48)
    else:
        centres = unit_vectors(rng, 4, 48)
        database, queries = clustered(rng, 1200, 48, centres), clustered(rng, 80, 48, centres)
    database[700:703] = database[100]  # duplicates of an item of the first block
    queries[0] = database[100]
    k, margin, block = 10, 16, 400
    stats = {}
    distances, indices = exact_knn(
        database, queries, k, device="cpu", block_database=block, margin=margin, stats=stats
    )
    assert stats["rescored"] < len(queries) * (len(database) // block) * (k + margin // 2)
    np.testing.assert_array_equal(indices[0, :4], [100, 700, 701, 702])
    np.testing.assert_array_equal(distances[0, :4], np.zeros(4, np.float32))
    check_against_float64(distances, indices, database, queries, k)
