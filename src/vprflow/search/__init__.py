"""k-nearest-neighbour search for segment retrieval (docs/methods.md §8), one module per
kind of search, numpy in and out.

Every search takes ``database [Nd, D]``, ``queries [Nq, D]`` and ``k`` and returns
``(distances [Nq, k'] float32, indices [Nq, k'] int64)``, squared L2, ``k' = min(k, Nd)``,
nearest first:

- :mod:`vprflow.search.flat`: faiss ``IndexFlatL2``, exact, the published search;
- :mod:`vprflow.search.exact`: the same top-k from blocked torch products, certified exact;
- :mod:`vprflow.search.approximate`: approximate faiss indexes (IVF, PQ, HNSW);
- :mod:`vprflow.search.topk`: merging top-k lists (shards) and comparing them.

Which function runs a ``retrieval.index`` is said once, by its
:data:`vprflow.search.indexes.SEARCH_INDEXES` entry
(:meth:`vprflow.search.indexes.SearchIndex.search`); the parameters' defaults are
:mod:`vprflow.search.defaults`.
"""
