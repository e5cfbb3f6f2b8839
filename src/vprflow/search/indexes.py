"""Every search index vprflow knows (a ``retrieval.index``), one :class:`SearchIndex`
entry each: the function that runs it and its parameters' defaults.

The search modules name faiss, and this one the exact search's torch module, with
``lazy_import``, so that planning reads this module (the schema's index names, the
defaults in every key) without importing either.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from vprflow.core.lazy import lazy_import
from vprflow.search import defaults
from vprflow.search.approximate import hnsw_knn, ivf_flat_knn, ivf_pq_knn
from vprflow.search.flat import flat_knn

exact = lazy_import("vprflow.search.exact")


@dataclass(frozen=True)
class SearchIndex:
    """A ``retrieval.index``: whether it returns the exact top-k (an approximate one makes
    the plan add an exact search, so the table can report the difference), the function
    that runs it, whether it runs on a GPU when there is one, and its parameters'
    defaults (``None``: chosen at run time by its function), filled into a method's
    ``retrieval.params`` before hashing (:func:`search_settings`).

    ``knn`` has the signature ``(database [Nd, D], queries [Nq, D], k, **params) ->
    (distances [Nq, k'] float32, indices [Nq, k'] int64)`` (see :mod:`vprflow.search`),
    plus ``device`` when ``uses_gpu``; :meth:`search` calls it. ``defaults`` are those of
    :mod:`vprflow.search.defaults`, which the functions also read. ``description``: what
    it is, in the config's words (the schema's ``index`` description lists every index's).
    """

    name: str
    exact: bool
    knn: Callable[..., Any]
    uses_gpu: bool = False
    defaults: dict = field(default_factory=dict)
    description: str = field(kw_only=True)

    def search(self, database, queries, k: int, params: dict | None = None, device="auto"):
        """Squared-L2 ``k`` nearest ``database`` rows of every query with this index and
        ``params`` (left out: :attr:`defaults`): ``(distances [Nq, k'] float32, indices
        [Nq, k'] int64)``, ``k' = min(k, Nd)``, nearest first. Rows of an approximate
        index may end in index -1 (fewer than k found). ``device`` (``"auto"``, ``"cpu"``,
        ``"cuda"``) is used by the indexes that run on a GPU."""
        params = dict(params or {})
        _check_search_params(self, params, "params")
        if self.uses_gpu:
            params["device"] = device
        return self.knn(database, queries, k, **params)


def _exact_knn(database, queries, k: int, **params):
    return exact.exact_knn(database, queries, k, **params)


SEARCH_INDEXES: dict[str, SearchIndex] = {
    index.name: index
    for index in (
        # faiss IndexFlatL2, published.
        SearchIndex(
            "flat",
            exact=True,
            knn=flat_knn,
            description="exact squared L2 (faiss IndexFlatL2, published)",
        ),
        SearchIndex(
            "exact_fast",
            exact=True,
            knn=_exact_knn,
            uses_gpu=True,
            defaults=defaults.EXACT,
            description="the same top-k from blocked torch products (bf16 candidates, "
            "float32 re-score; GPU with device auto)",
        ),
        SearchIndex(
            "ivf_flat",
            exact=False,
            knn=ivf_flat_knn,
            defaults=defaults.IVF_FLAT,
            description="approximate: faiss inverted lists of full vectors",
        ),
        SearchIndex(
            "ivf_pq",
            exact=False,
            knn=ivf_pq_knn,
            defaults=defaults.IVF_PQ,
            description="approximate: faiss inverted lists of product-quantised vectors",
        ),
        SearchIndex(
            "hnsw",
            exact=False,
            knn=hnsw_knn,
            defaults=defaults.HNSW,
            description="approximate: faiss HNSW graph",
        ),
    )
}


def search_index(name: str) -> SearchIndex:
    if name not in SEARCH_INDEXES:
        raise ValueError(f"unknown search index {name!r}; expected one of {sorted(SEARCH_INDEXES)}")
    return SEARCH_INDEXES[name]


def search_settings(retrieval: dict) -> dict:
    """A ``retrieval`` section (``index``, ``params``) with the index's parameter defaults
    filled into ``params``, so a key records what ran; a parameter the index does not
    take is refused by name."""
    index = search_index(retrieval["index"])
    params = retrieval["params"]
    _check_search_params(index, params, "retrieval.params")
    return {**retrieval, "params": {**index.defaults, **params}}


def _check_search_params(index: SearchIndex, params: dict, what: str) -> None:
    unknown = sorted(set(params) - set(index.defaults))
    if unknown:
        raise ValueError(
            f"{what} {unknown} are not parameters of index {index.name!r}; "
            f"it takes {sorted(index.defaults) or 'none'}"
        )
