"""Exact squared-L2 k-NN in torch (``retrieval.index: exact_fast``): faiss
``IndexFlatL2``'s top-k (:func:`vprflow.search.flat.flat_knn`) from low-precision products,
certified exact, on CPU or GPU.

:func:`exact_knn` returns ``(distances [Nq, k'] float32, indices [Nq, k'] int64)`` with
``k' = min(k, Nd)``, nearest first, like every search of :mod:`vprflow.search`.

How it works
------------
For each (query block, database block) the products ``q . r`` are computed in low
precision (``candidate_dtype``, float32 accumulation) only to pick candidates; every
candidate is then re-scored exactly as ``((q - r) ** 2).sum()`` in float32 and the k best
by (distance, index) are kept across blocks. The re-score uses the direct difference
form rather than faiss's BLAS expansion ``|q|^2 + |r|^2 - 2 q.r``: it has no cancellation
(its error is relative to the distance itself, so near-duplicates keep their order and
never go negative) and it is the formula of faiss's own SIMD path for small batches. On
1024-d unit vectors its largest error against float64 was 3.5e-7 (faiss flat: 2.2e-7 to
4.8e-7 depending on the batch) and it differs from faiss flat's values by at most 6e-7,
so the result is faiss flat's top-k up to ties within float32 rounding.

The candidate cut-off is certified, not hoped for. :func:`_error_bound` bounds, from the
data, how far the low-precision distance ``d~ = |q|^2 + |r|^2 - 2 (q . r)~`` can be from the
float32 re-score ``d``: input rounding by Cauchy-Schwarz on the exact residuals
``q - lp(q)``, worst-case float32 accumulation (any summation order), and the rounding of
the product's output, taken relative to the product itself. A block hands over its
``k + margin`` best candidates by ``d~``; every item left out then has ``d`` at least
(largest ``d~`` kept) minus the bound. Where that floor does not clear the k-th distance
kept (which later blocks can only lower), the row takes, in one more pass, every item
whose floor does not clear it. So the result is exact for any finite data, duplicates and
non-normalised vectors included; ``margin`` only sets how often a row needs that pass.
For unit vectors in 1024-d the bound is about 0.008 in distance with bf16 (0.0068 input
rounding, 7e-4 output rounding near a typical cut-off, 9e-4 float32 slack) and 9e-4 with
float32 candidates.

Keying and ranking every item of a ``[block_queries, block_database]`` product would cost
about half as much as the bf16 product itself on CPUs. So wide blocks are cut into groups
of :data:`GROUP` strided columns: one max-reduction over the raw product (bf16 read through
its bit patterns as int16) bounds each group's keys from below; the ``k + margin`` groups
with the smallest bounds are keyed item by item, and every other item has a key of at
least the largest bound expanded, which the certificate uses like the largest key kept
(:func:`_select`). Database blocks whose norms differ are reordered by norm, so that a
group's bound stays close to its items' keys. Candidates are re-scored in two steps: the
``k + margin / 2`` best by key (fewer in later database blocks, where the running k-th
distances already rule candidates out: as many as nine rows in ten need), then the rest
only for rows the certificate does not clear.
On one Zen 4 core (34,510 x 4,096 1024-d unit vectors, k 50, runs interleaved with faiss
flat) bf16 candidates took 1.48 CPU s against faiss flat's 2.73 (1.90 s before these
changes): 0.8 s of product (about 360 GFLOP/s per core), the rest selection, 87-91
re-scored candidates per query and merging. The bf16 product alone bounds the speed-up over
faiss flat's float32 GEMM (about 100 GFLOP/s per core) at about 3.5x.

int8 candidates (``torch._int_mm``, about 1.45x the bf16 GEMM per core on an AVX512-VNNI
Zen 4) were measured and left out: symmetric per-row int8 rounding leaves residuals about
7x bf16's (``|x - lp(x)|`` 0.0075 against 0.0011 for 1024-d unit vectors), the certified
bound grows from 0.008 to 0.044, and a 34,510-row block then needs a median of 390
candidates per row instead of 76 (90th percentile 460 against 85). Re-scoring one
candidate costs about as much CPU as 100 bf16 products, so int8 loses more than it saves.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch

from vprflow.core.devices import resolve_device
from vprflow.search.defaults import EXACT as _EXACT
from vprflow.search.inputs import as_matrix, non_negative_int, positive_int
from vprflow.search.topk import NO_INDEX

CANDIDATE_DTYPES = {"bfloat16": torch.bfloat16, "float16": torch.float16, "float32": torch.float32}

# Extra candidates per block beyond k, per candidate dtype. Correctness does not depend on
# it (the cut-off is certified, and rows it does not cover get one exactly sized extra
# pass); it trades re-scoring up to margin extra candidates per row (margin / 2 for every
# row, the rest only for rows that need them) against that pass. Measured
# k = 50 on 20,000-row blocks of 1024-d unit vectors, 200 queries, the fewest candidates the
# certificate accepts: bf16 random data median 77 / max 100, clustered 68 / 83; float32 at
# most 59. So bf16 takes 64 extra; float32 (bound ~10x smaller) 16; float16 (8x finer input
# rounding than bf16) 24. With these, 65,536-row blocks of random unit vectors widened no
# row either; denser data may widen more rows, at a cost, never wrongly.
DEFAULT_MARGINS = {"bfloat16": 64, "float16": 24, "float32": 16}

_UNIT32 = 2.0**-24  # float32 unit roundoff
# Columns per group in candidate selection (_select): the product is reduced to one bound per
# group, and only the best groups are keyed item by item.
GROUP = 16


def exact_knn(
    database: np.ndarray,
    queries: np.ndarray,
    k: int,
    *,
    device: str = "auto",
    block_queries: int = _EXACT["block_queries"],
    block_database: int = _EXACT["block_database"],
    candidate_dtype: str = _EXACT["candidate_dtype"],
    margin: int | None = _EXACT["margin"],
    stats: dict | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact squared-L2 k-NN: ``database [Nd, D]``, ``queries [Nq, D]`` ->
    ``(distances [Nq, k'] float32, indices [Nq, k'] int64)``, ``k' = min(k, Nd)``.

    Distances are float32 ``((q - r) ** 2).sum()``; rows are sorted by (distance, index),
    so exact ties go to the lower index. Equal to faiss ``IndexFlatL2`` except where two
    distances are within float32 rounding of each other (see the module docstring).

    ``device``: ``"auto"``, ``"cpu"``, ``"cuda"`` (see :func:`vprflow.core.devices.resolve_device`).
    The other settings default to :data:`vprflow.search.defaults.EXACT` (the search
    stage passes them from its key).
    ``candidate_dtype``: ``"bfloat16"``, ``"float16"`` (slow on CPUs) or ``"float32"``, the
    precision of the products that choose candidates; like ``margin`` (extra candidates
    per block beyond k, ``None``: :data:`DEFAULT_MARGINS` by dtype) it changes speed, never
    the result.
    Peak memory is about ``block_queries x block_database`` products in the GEMM's output
    dtype (bf16 on CPUs: 0.5 GiB at the defaults; float32 on CUDA or with float32
    candidates), plus as much float32 for blocks too narrow for selection by column groups
    (fewer than ``4 * GROUP * (k + margin)`` columns), a 16 MiB re-scoring buffer (64 MiB
    on GPUs) and the two blocks, independent of ``Nd`` and ``Nq``; the inputs may be
    memory-mapped.
    ``stats``, when given, is filled with counters: ``rescored`` (candidate pairs
    re-scored) and ``widened`` (row-block pairs whose candidate list had to grow past
    ``k + margin``).
    """
    database = as_matrix(database, "database")
    queries = as_matrix(queries, "queries")
    if database.shape[1] != queries.shape[1]:
        raise ValueError(
            f"database has dimension {database.shape[1]} but queries {queries.shape[1]}"
        )
    k = non_negative_int("k", k)
    block_queries = positive_int("block_queries", block_queries)
    block_database = positive_int("block_database", block_database)
    if candidate_dtype not in CANDIDATE_DTYPES:
        raise ValueError(
            f"unknown candidate_dtype {candidate_dtype!r}; expected one of "
            f"{sorted(CANDIDATE_DTYPES)}"
        )
    low = CANDIDATE_DTYPES[candidate_dtype]
    margin = non_negative_int(
        "margin", DEFAULT_MARGINS[candidate_dtype] if margin is None else margin
    )
    target = resolve_device(device)
    counters = stats if stats is not None else {}
    counters.setdefault("rescored", 0)
    counters.setdefault("widened", 0)

    n_db, n_q = len(database), len(queries)
    k_out = min(k, n_db)
    distances = np.full((n_q, k_out), np.inf, dtype=np.float32)
    indices = np.full((n_q, k_out), NO_INDEX, dtype=np.int64)
    if k_out == 0 or n_q == 0:
        return distances, indices

    # Database blocks outside, query blocks inside: each database block is converted and
    # moved to the device once, and only the small [Nq, k] running results go back and forth.
    for db_start in range(0, n_db, block_database):
        ref = _by_norm(_side(_block(database, db_start, block_database, target), low))
        for q_start in range(0, n_q, block_queries):
            query = _side(_block(queries, q_start, block_queries, target), low)
            rows = slice(q_start, q_start + len(query.x))
            best_d, best_i = _search_block(
                query,
                ref,
                torch.from_numpy(distances[rows]).to(target),
                torch.from_numpy(indices[rows]).to(target),
                db_start,
                k_out,
                margin,
                counters,
            )
            distances[rows] = best_d.cpu().numpy()
            indices[rows] = best_i.cpu().numpy()
    return distances, indices


class _Side(NamedTuple):
    """One block of vectors prepared for the low-precision product and its error bound.

    ``x [n, D]`` float32; ``low [n, D]`` the block scaled by ``scale`` (a power of two) and
    cast to the candidate dtype; ``sq_norm``, ``norm``, ``hi_norm``, ``lo_norm`` ``[n]``:
    ``|x|^2``, ``|x|``, ``|lp(x)|``, ``|x - lp(x)|`` (unscaled, rounding residual exact).
    ``order``: None, or ``[n]`` when the rows of ``low`` are those of ``x`` reordered
    (``low[j]`` is row ``order[j]``; see :func:`_by_norm`).
    """

    x: torch.Tensor
    low: torch.Tensor
    scale: float
    sq_norm: torch.Tensor
    norm: torch.Tensor
    hi_norm: torch.Tensor
    lo_norm: torch.Tensor
    order: torch.Tensor | None = None


def _by_norm(side: _Side) -> _Side:
    """The database block with the rows of ``low`` reordered by norm when the norms differ
    (by more than 0.1%), so that each column group of :func:`_select` (columns ``j + t *
    groups``) holds consecutive norms and its bound stays close to its items' keys. Costs
    one copy of ``low`` per database block; changes speed only."""
    sq = side.sq_norm
    if len(sq) < 2 or float(sq.max() - sq.min()) <= 1e-3 * float(sq.max()):
        return side
    order = torch.argsort(sq, stable=True)
    groups = len(sq) // GROUP
    whole = groups * GROUP
    order[:whole] = order[:whole].view(groups, GROUP).T.reshape(-1)
    return side._replace(low=side.low[order], order=order)


def _side(x: torch.Tensor, low: torch.dtype) -> _Side:
    """The block ``x [n, D]`` float32 prepared for the product (see :class:`_Side`)."""
    if low == torch.float32:
        sq_norm = _finite_sq_norm(torch.linalg.vecdot(x, x))
        norm = sq_norm.sqrt()
        # No explicit rounding, but the GEMM itself may round its inputs (TF32 or bf16
        # modes chosen through torch's float32 matmul precision): bound it elementwise.
        unit = _float32_matmul_unit(x.device)
        return _Side(x, x, 1.0, sq_norm, norm, norm * (1 + unit), norm * unit)
    scale = 1.0
    if low == torch.float16:
        # float16 overflows at 65504 and loses relative precision below 6e-5: scale the block
        # by a power of two (exact) so its largest element lies in [0.5, 1).
        largest = float(x.abs().max()) if x.numel() else 0.0
        if largest > 0:
            scale = math.ldexp(1.0, -math.frexp(largest)[1])
    n, dim = x.shape
    rounded = torch.empty((n, dim), dtype=low, device=x.device)
    sq_norm, hi_norm, lo_norm = torch.empty((3, n), dtype=torch.float32, device=x.device)
    # By chunks of rows through one reused float32 buffer, so that the block is read from
    # memory once and each chunk stays in cache between its steps: whole-block float32
    # temporaries (256 MiB each for 65,536 x 1024) cost more in page faults and memory
    # traffic than the arithmetic. Every value is a reduction along a row, the same as
    # over the whole block.
    rows = max(1, min(n, _side_elements(x.device) // max(dim, 1)))
    buffer = torch.empty((rows, dim), dtype=torch.float32, device=x.device)
    for r0 in range(0, n, rows):
        part, cut = x[r0 : r0 + rows], slice(r0, r0 + rows)
        torch.linalg.vecdot(part, part, out=sq_norm[cut])
        hi = buffer[: len(part)]
        if scale == 1.0:
            rounded[cut] = part
        else:
            rounded[cut] = torch.mul(part, scale, out=hi)
        hi.copy_(rounded[cut])
        if scale != 1.0:
            hi.div_(scale)
        torch.linalg.vector_norm(hi, dim=1, out=hi_norm[cut])
        torch.linalg.vector_norm(hi.sub_(part), dim=1, out=lo_norm[cut])
    norm = _finite_sq_norm(sq_norm).sqrt()
    return _Side(x, rounded, scale, sq_norm, norm, hi_norm, lo_norm)


def _finite_sq_norm(sq_norm: torch.Tensor) -> torch.Tensor:
    # The certified bound needs finite data and norms (NaN has no place in a ranking anyway);
    # a NaN or inf anywhere in a row shows in its squared norm.
    if not bool(torch.isfinite(sq_norm).all()):
        raise ValueError("non-finite values (or squared norms beyond float32) in the vectors")
    return sq_norm


def _side_elements(device: torch.device) -> int:
    # CPU: 16 MiB of float32, 16 chunks per 65,536 x 1024 block. Smaller chunks, nearer a
    # core's cache, ran faster on one thread (1 MiB: 3x the whole-block pass) but each torch
    # step has a fixed multi-threaded cost that grows many times over on a loaded machine
    # (1 MiB on two busy cores: up to 8x slower). GPU: 256 MiB, enough work per launch.
    return 1 << 22 if device.type == "cpu" else 1 << 26


def _float32_matmul_unit(device: torch.device) -> float:
    """Unit roundoff of the inputs of a float32 GEMM under torch's matmul precision setting."""
    precision = torch.get_float32_matmul_precision()
    if device.type == "cuda" and precision == "highest" and torch.backends.cuda.matmul.allow_tf32:
        precision = "high"
    return {"highest": 0.0, "high": 2.0**-11}.get(precision, 2.0**-8)


def _product(query: _Side, ref: _Side) -> tuple[torch.Tensor, float, float]:
    """``query.x @ ref.x.T`` from the low-precision blocks: ``(raw [nq, nr], factor, unit)``,
    the product being ``s~ = float32(raw) * factor`` (``factor`` a power of two undoing the
    float16 scaling, so exact), ``unit`` the unit roundoff of the output rounding (float32
    when the backend writes float32). ``raw`` stays in the GEMM's output dtype: converting
    it whole would cost more than choosing candidates from it (see :func:`_select`).

    The bound assumes float32 accumulation and at most one rounding of the output to the
    candidate dtype: true of oneDNN on CPUs, and on CUDA the float32-output GEMM is used,
    so cuBLAS's reduced-precision split-K reductions (bf16/fp16 outputs only) never apply.
    """
    if query.low.dtype == torch.float32:
        return query.low @ ref.low.T, 1.0, _UNIT32
    factor = 1.0 / (query.scale * ref.scale)
    if query.low.device.type != "cpu":
        # CUDA GEMMs can write float32 from bf16/fp16 inputs: no rounding of the output.
        try:
            return torch.mm(query.low, ref.low.T, out_dtype=torch.float32), factor, _UNIT32
        except (RuntimeError, TypeError, NotImplementedError):
            pass
    return query.low @ ref.low.T, factor, torch.finfo(query.low.dtype).eps / 2


def _keys(values: torch.Tensor, factor: float, sq_norm: torch.Tensor) -> torch.Tensor:
    """Ranking keys ``|r|^2 - 2 s~`` in float32 from raw products ``values [n, c]`` and
    ``sq_norm`` (``[c]`` or ``[n, c]``), overwriting ``values`` when it is float32 already
    (pass a copy to keep it).
    Each step rounds monotonically, so a larger raw value never gives a smaller s~ nor, with
    the same or a smaller ``|r|^2``, a larger key: what the group bounds of :func:`_select`
    rely on."""
    return values.float().mul_(-2.0 * factor).add_(sq_norm)


def _error_bound(query: _Side, ref: _Side) -> torch.Tensor:
    """``[nq]``: a bound, over the pairs of a query row with the block, on ``|d' - d|`` where
    ``d' = |q|^2 + |r|^2 - 2 s'`` uses the low-precision product ``s'`` before its output
    rounding (handled in :func:`_search_block`) and ``d`` is the float32 re-score
    ``((q - r) ** 2).sum()``. Rounding errors, after Higham's bounds:

    - inputs: ``q . r - lp(q) . lp(r) = lp(q) . r_lo + q_lo . lp(r) + q_lo . r_lo`` with the
      exact residuals ``q_lo = q - lp(q)``; Cauchy-Schwarz on each term;
    - float32 accumulation of the product: ``2 gamma |lp(q)| |lp(r)|`` (any summation
      order; doubled for round-toward-zero accumulators such as GPU tensor cores);
    - float32 norms, the re-score, and the handful of additions forming and testing
      ``d~``: each at most ``gamma (|q| + |r|)^2``, three of them;
    - float16 only: the subnormal spacing of the product.

    ``gamma = n u / (1 - n u)``, ``u = 2^-24``, ``n = D + 8``. The sum is inflated by 1% for
    the rounding of the bound's own arithmetic.
    """
    n = query.x.shape[1] + 8
    gamma = n * _UNIT32 / (1 - n * _UNIT32)
    r_hi, r_lo, r_norm = ref.hi_norm.max(), ref.lo_norm.max(), ref.norm.max()
    dot = query.lo_norm * r_hi + query.hi_norm * r_lo + query.lo_norm * r_lo
    dot = dot + 2 * gamma * query.hi_norm * r_hi
    if query.low.dtype == torch.float16:
        info = torch.finfo(torch.float16)
        dot = dot + info.smallest_normal * info.eps / (query.scale * ref.scale)
    return 1.01 * (2 * dot + 3 * gamma * (query.norm + r_norm) ** 2)


def _search_block(
    query: _Side,
    ref: _Side,
    run_d: torch.Tensor,
    run_i: torch.Tensor,
    offset: int,
    k: int,
    margin: int,
    counters: dict,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Merge one database block into the running top-k ``run_d, run_i [nq, k]``."""
    raw, factor, unit = _product(query, ref)
    bound = _error_bound(query, ref)
    unit = unit / (1 - unit)  # relative to the rounded output rather than the exact one
    ref_sq_max, ref_sq_min = ref.sq_norm.max(), ref.sq_norm.min()

    def key_floor(c: torch.Tensor) -> torch.Tensor:
        # A lower bound on key_j - 2 u |s_j| for every key_j >= c, s_j the rounded product.
        # For s_j >= 0, s_j = (|r_j|^2 - key_j) / 2 gives c - u (max |r|^2 - c); for s_j < 0,
        # key_j - 2 u |s_j| >= max(min |r|^2, (1 - u) c). Near typical cut-offs this is about
        # 10x sharper than the worst case 2 u |q| |r|.
        return torch.minimum(c - unit * (ref_sq_max - c), torch.maximum(ref_sq_min, (1 - unit) * c))

    n_block = raw.shape[1]
    count = min(n_block, k + margin)
    # Columns of `raw` are the rows of ref.low: in ref.order when the block was reordered.
    col_sq = ref.sq_norm if ref.order is None else ref.sq_norm[ref.order]
    # Every item left out of `cand` has a key of at least `threshold` [nq].
    cand, cand_key, threshold, key = _select(raw, factor, col_sq, count)
    # Re-scored in two steps: first the k + margin / 2 best candidates by key, then the rest
    # only for the rows whose certificate needs them (most need fewer than k + margin).
    first = min(count, k + margin // 2)
    rest = None
    kth = run_d[:, k - 1]
    if first > 1 and bool(torch.isfinite(kth).all()):
        # Earlier blocks' k-th distances already rule out every candidate whose key floor
        # clears them (the certificate below, applied before re-scoring). The first step
        # takes, for all rows, as many as nine rows in ten need; the others take the rest
        # in the second step. On a second 1024-d random block of 34,464 rows after one of
        # 65,536, k 50: rows needed a median of 42, 90% 54, at most 72 of the 82.
        cand_key, by_key = torch.sort(cand_key, dim=1)
        cand = cand.gather(1, by_key)
        need_key = kth - query.sq_norm + bound
        needed = (key_floor(cand_key[:, :first]) <= need_key[:, None]).sum(1)
        typical = needed.kthvalue(math.ceil(0.9 * len(needed))).values
        first = max(1, min(first, int(typical)))
    if first < count:
        sorted_key, by_key = torch.sort(cand_key, dim=1)
        cand = cand.gather(1, by_key)
        cand, rest, rest_threshold = cand[:, :first], cand[:, first:], threshold
        threshold = torch.minimum(threshold, sorted_key[:, first])
        del sorted_key, by_key
    del cand_key
    done = first  # items of the block re-scored so far for the rows in `pending`
    best_d = best_i = run_d  # replaced by the first pass, which covers every row
    pending = None  # None: all rows
    carried = None  # (distances, indices) re-scored in the first step, for the rows in `pending`
    while True:
        # Candidates in index order: _merge's tie rule needs it, and the gather is more local.
        cand = torch.sort(cand if ref.order is None else ref.order[cand], dim=1).values
        rows_q = query.x if pending is None else query.x[pending]
        cand_d = _rescore(rows_q, ref.x, cand)
        counters["rescored"] += cand.numel()
        if carried is not None:
            cand, position = torch.sort(torch.cat([carried[1], cand], 1), dim=1)
            cand_d = torch.cat([carried[0], cand_d], 1).gather(1, position)
        prev_d = run_d if pending is None else run_d[pending]
        prev_i = run_i if pending is None else run_i[pending]
        merged_d, merged_i = _merge(prev_d, prev_i, cand_d, cand + offset, k)
        if pending is None:
            best_d, best_i = merged_d, merged_i
        else:
            best_d[pending], best_i[pending] = merged_d, merged_i
        if done == n_block:
            break
        # An item left out has key_j >= threshold, so its float32 distance is at least
        # |q|^2 + key_floor(threshold) - bound. If that exceeds the k-th distance kept
        # (which later blocks only lower), nothing left out can enter the top-k, not even as
        # a tie. Otherwise those rows take the rest of their candidates and, if still not
        # clear, every item whose floor does not clear it: one more pass, sized exactly.
        sq = query.sq_norm if pending is None else query.sq_norm[pending]
        limit = bound if pending is None else bound[pending]
        need_key = merged_d[:, k - 1] - sq + limit  # items need key_floor(key) > need_key
        unsafe = ~(key_floor(threshold) > need_key)
        if not bool(unsafe.any()):
            break
        where = torch.nonzero(unsafe).squeeze(1)
        pending = where if pending is None else pending[where]
        if rest is not None:  # the first step covered every row: `pending` indexes `rest`
            carried = (cand_d[where], cand[where])
            cand, threshold, done, rest = rest[pending], rest_threshold[pending], count, None
            continue
        carried = None  # from scratch: the new candidates include those re-scored before
        counters["widened"] += len(pending)
        rows_key = key[pending] if key is not None else _keys(raw[pending], factor, col_sq)
        unclear = (key_floor(rows_key) <= need_key[where, None]).sum(1).max()
        done = min(n_block, max(int(unclear) + 1, done + 1))
        cand_key, cand = torch.topk(rows_key, done, dim=1, largest=False, sorted=False)
        threshold = cand_key.amax(1)
        del rows_key, cand_key
    return best_d, best_i


def _select(
    raw: torch.Tensor, factor: float, sq_norm: torch.Tensor, count: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """``count`` candidates of small key per row of the raw product ``[n, m]``:
    ``(columns [n, count], their keys [n, count], threshold [n], key)``, every item left
    out having a key of at least ``threshold``; ``key`` is the full ``[n, m]`` key matrix
    when it was built, else None.

    Blocks with many columns per candidate are cut into groups of :data:`GROUP` columns.
    A group's largest raw value keyed with its smallest ``|r|^2`` bounds every key in the
    group from below (:func:`_keys` is monotone). The ``count`` groups with the smallest
    bounds are expanded and keyed item by item, and the items of every other group have
    keys of at least the largest bound expanded. So only one integer max-reduction reads the
    whole product, and conversion and top-k work on ``count * GROUP`` items per row.
    """
    n, m = raw.shape
    groups = m // GROUP
    if groups < 4 * count or raw.element_size() not in _SIGNED:
        key = _keys(raw, factor, sq_norm)
        cand_key, cand = torch.topk(key, count, dim=1, largest=False, sorted=False)
        return cand, cand_key, cand_key.amax(1), key
    whole = groups * GROUP
    # Group j is the columns j + t * groups, t < GROUP: strided, so the max-reduction runs
    # along contiguous rows (3x faster than over short contiguous runs).
    grouped = raw[:, :whole].view(n, GROUP, groups)
    group_sq = sq_norm[:whole].view(GROUP, groups)
    bounds = _keys(_group_max(grouped, 1), factor, group_sq.amin(0))
    low_bounds, chosen = torch.topk(bounds, count, dim=1, largest=False, sorted=False)
    del bounds
    values = grouped.gather(2, chosen[:, None, :].expand(n, GROUP, count))
    keys = _keys(values, factor, group_sq[:, chosen].transpose(0, 1))  # [n, GROUP, count]
    del values
    cand_key, position = torch.topk(keys.view(n, -1), count, dim=1, largest=False, sorted=False)
    del keys
    cand = chosen.gather(1, position % count).add_(
        position.div_(count, rounding_mode="floor") * groups
    )
    if whole < m:  # the last, partial group: its few items compete with the candidates
        tail_key = _keys(raw[:, whole:].clone(), factor, sq_norm[whole:])  # raw stays
        tail = torch.arange(whole, m, device=raw.device).expand(n, m - whole)
        cand_key, position = torch.topk(
            torch.cat([cand_key, tail_key], 1), count, dim=1, largest=False, sorted=False
        )
        cand = torch.cat([cand, tail], 1).gather(1, position)
    # Left out: items of other groups (keys >= their bounds >= the largest bound chosen)
    # and items keyed here but not kept (keys >= the largest key kept).
    return cand, cand_key, torch.minimum(low_bounds.amax(1), cand_key.amax(1)), None


# Floating-point dtypes' bit patterns as signed integers of the same width.
_SIGNED = {2: torch.int16, 4: torch.int32}


def _group_max(groups: torch.Tensor, dim: int) -> torch.Tensor:
    """An upper bound, in the same dtype, on the largest value of each group, reducing
    ``dim``: the largest value when it is positive, else zero.

    Floats are reduced through their bit patterns read as signed integers, which order
    non-negative floats as their values and put every negative float (sign bit set) below
    them: faster than torch's bfloat16 max on CPUs, and one pass over the product.
    """
    if not groups.is_floating_point():
        return groups.amax(dim)
    bits = groups.view(_SIGNED[groups.element_size()]).amax(dim).clamp_(min=0)
    return bits.view(groups.dtype)


def _rescore(query: torch.Tensor, ref: torch.Tensor, cand: torch.Tensor) -> torch.Tensor:
    """Float32 ``((q - r) ** 2).sum()`` for ``query [n, D]`` and the rows ``cand [n, c]`` of
    ``ref [m, D]`` -> ``[n, c]``.

    Gathers many rows' candidates at a time into one reused buffer of about
    :func:`_rescore_elements` floats: bounded memory (a fresh multi-GB gather is several
    times slower, mostly page faults and memory traffic), yet few torch steps, since each
    step's fixed cost (thread start-up and barriers) grows many times over on a loaded
    machine. The sum runs along contiguous rows of ``D``, so its value does not depend on
    the chunking.
    """
    n, c = cand.shape
    dim = ref.shape[1]
    out = torch.empty((n, c), dtype=torch.float32, device=ref.device)
    budget = _rescore_elements(ref.device)
    cols = max(1, min(c, budget // dim))
    rows = max(1, min(n, budget // (cols * dim)))
    buffer = torch.empty((rows * cols, dim), dtype=torch.float32, device=ref.device)
    for r0 in range(0, n, rows):
        for c0 in range(0, c, cols):
            chunk = cand[r0 : r0 + rows, c0 : c0 + cols]
            diff = buffer[: chunk.numel()]
            torch.index_select(ref, 0, chunk.reshape(-1), out=diff)
            diff = diff.view(*chunk.shape, dim).sub_(query[r0 : r0 + rows, None, :])
            target = out[r0 : r0 + rows, c0 : c0 + cols]
            if cols == c:  # whole rows of `out`: sum straight into it
                torch.sum(diff.square_(), -1, out=target)
            else:
                target.copy_(diff.square_().sum(-1))
    return out


def _rescore_elements(device: torch.device) -> int:
    # CPU: 16 MiB, within a server's L3 cache, about 85 steps per 4,096-query block at k 50.
    # A core-sized 4 MiB (340 steps) was as fast on one idle thread, but each step has a
    # fixed multi-threaded cost that grows many times over under load (2.5x slower on two
    # busy cores); 64 MiB, out of cache, lost on a lightly loaded machine.
    # GPU: 64 MiB, enough work per kernel launch.
    return 1 << 22 if device.type == "cpu" else 1 << 24


def _merge(
    dist_a: torch.Tensor, idx_a: torch.Tensor, dist_b: torch.Tensor, idx_b: torch.Tensor, k: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per row, the k best by (distance, index) of ``[n, a]`` and ``[n, b]`` -> ``[n, k]``.

    Needs every row of ``a`` sorted by (distance, index), ``b`` sorted by index, and every
    index of ``a`` below those of ``b`` (earlier blocks; padding has distance inf): then the
    concatenation is in index order among equal distances, and one stable sort suffices.
    """
    dist = torch.cat([dist_a, dist_b], 1)
    idx = torch.cat([idx_a, idx_b], 1)
    order = torch.argsort(dist, dim=1, stable=True)[:, :k]
    return dist.gather(1, order), idx.gather(1, order)


def _block(array: np.ndarray, start: int, size: int, device: torch.device) -> torch.Tensor:
    """Rows ``[start, start + size)`` of ``array`` as a float32 tensor on ``device``."""
    block = torch.from_numpy(np.ascontiguousarray(array[start : start + size], dtype=np.float32))
    return block.to(device)
