"""Approximate squared-L2 k-NN with faiss indexes: one function per index, each
``(database [Nd, D], queries [Nq, D], k, **params) -> (distances [Nq, k'] float32,
indices [Nq, k'] int64)``, ``k' = min(k, Nd)``, nearest first.

Parameters left out take the defaults of :mod:`vprflow.search.defaults` (which the
search stage's keys record).

IVF training is deterministic: the coarse and PQ k-means use ``seed``. HNSW graph
construction is parallel and therefore only reproducible with one OpenMP thread.
Approximate indexes may return fewer than k' results for a row, padded as faiss does
with index -1 and distance 3.4e38 (float32 max).
"""

from __future__ import annotations

import math

import numpy as np

from vprflow.core.lazy import lazy_import
from vprflow.search.defaults import HNSW as _HNSW
from vprflow.search.defaults import IVF_FLAT as _IVF_FLAT
from vprflow.search.defaults import IVF_PQ as _IVF_PQ
from vprflow.search.inputs import empty_result, faiss_inputs, positive_int

faiss = lazy_import("faiss")


def ivf_flat_knn(
    database: np.ndarray,
    queries: np.ndarray,
    k: int,
    *,
    nlist: int | None = _IVF_FLAT["nlist"],
    nprobe: int = _IVF_FLAT["nprobe"],
    seed: int = _IVF_FLAT["seed"],
) -> tuple[np.ndarray, np.ndarray]:
    """faiss ``IVF<nlist>,Flat``: ``nlist`` (``None``: ``min(4 sqrt(Nd), Nd / 39)``, at
    least 1) lists, ``nprobe`` of them searched (capped at nlist), ``seed`` for the
    k-means training."""
    return _ivf_knn(database, queries, k, nlist, nprobe, seed)


def ivf_pq_knn(
    database: np.ndarray,
    queries: np.ndarray,
    k: int,
    *,
    nlist: int | None = _IVF_PQ["nlist"],
    nprobe: int = _IVF_PQ["nprobe"],
    seed: int = _IVF_PQ["seed"],
    m: int | None = _IVF_PQ["m"],
    nbits: int = _IVF_PQ["nbits"],
) -> tuple[np.ndarray, np.ndarray]:
    """faiss ``IVF<nlist>,PQ<m>x<nbits>``: as :func:`ivf_flat_knn` plus ``m``
    sub-quantizers (``None``: the largest divisor of D up to D / 16) of ``nbits`` bits;
    needs ``Nd >= 2 ** nbits``. Distances are the PQ approximations."""
    return _ivf_knn(database, queries, k, nlist, nprobe, seed, pq=(m, nbits))


def hnsw_knn(
    database: np.ndarray,
    queries: np.ndarray,
    k: int,
    *,
    M: int = _HNSW["M"],
    ef_search: int = _HNSW["ef_search"],
    ef_construction: int = _HNSW["ef_construction"],
) -> tuple[np.ndarray, np.ndarray]:
    """faiss ``IndexHNSWFlat`` with ``M`` links per node, ``ef_construction`` and
    ``ef_search`` (raised to k when smaller)."""
    database, queries, k_out = faiss_inputs(database, queries, k)
    if k_out == 0 or len(queries) == 0:
        return empty_result(len(queries), k_out)
    built = faiss.IndexHNSWFlat(database.shape[1], positive_int("M", M))
    built.hnsw.efConstruction = positive_int("ef_construction", ef_construction)
    built.add(database)
    # A search beam narrower than k cannot return k neighbours.
    built.hnsw.efSearch = max(positive_int("ef_search", ef_search), k_out)
    distances, indices = built.search(queries, k_out)
    return distances, indices.astype(np.int64, copy=False)


def _ivf_knn(
    database: np.ndarray,
    queries: np.ndarray,
    k: int,
    nlist: int | None,
    nprobe: int,
    seed: int,
    pq: tuple[int | None, int] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """An IVF index over flat vectors, or over PQ codes when ``pq = (m, nbits)``."""
    database, queries, k_out = faiss_inputs(database, queries, k)
    if k_out == 0 or len(queries) == 0:
        return empty_result(len(queries), k_out)
    n_db, dim = database.shape
    if nlist is None:
        nlist = max(1, min(round(4 * math.sqrt(n_db)), n_db // 39))
    nlist = positive_int("nlist", nlist)
    if nlist > n_db:
        raise ValueError(f"nlist={nlist} exceeds the {n_db} database vectors")
    if pq is None:
        built = faiss.index_factory(dim, f"IVF{nlist},Flat")
    else:
        m, nbits = pq
        m = positive_int("m", m if m is not None else _default_pq_m(dim))
        nbits = positive_int("nbits", nbits)
        if dim % m:
            raise ValueError(f"m={m} must divide the dimension {dim}")
        if n_db < 2**nbits:
            raise ValueError(f"nbits={nbits} needs at least {2**nbits} vectors, got {n_db}")
        built = faiss.index_factory(dim, f"IVF{nlist},PQ{m}x{nbits}")
    ivf = faiss.downcast_index(faiss.extract_index_ivf(built))
    seed = int(seed)
    ivf.cp.seed = seed
    if pq is not None:
        ivf.pq.cp.seed = seed
        # The factory turns on polysemous code reordering: slow (simulated annealing) and
        # only useful for polysemous filtering, which searches do not use.
        ivf.do_polysemous_training = False
    built.train(database)
    built.add(database)
    ivf.nprobe = min(positive_int("nprobe", nprobe), nlist)
    distances, indices = built.search(queries, k_out)
    return distances, indices.astype(np.int64, copy=False)


def _default_pq_m(dim: int) -> int:
    target = max(1, dim // 16)
    return max(m for m in range(1, target + 1) if dim % m == 0)
