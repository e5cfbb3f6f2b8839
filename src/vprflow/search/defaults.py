"""The search functions' parameters and their defaults (``None``: chosen at run time by
the function), as data: the functions take them as keyword defaults, and planning fills
them into every key (:func:`vprflow.search.indexes.search_settings`) without importing
torch or faiss."""

# exact_knn: none of these changes the result, only speed and memory. margin None: by
# candidate dtype (vprflow.search.exact.DEFAULT_MARGINS).
EXACT = {
    "candidate_dtype": "bfloat16",
    "block_queries": 4096,
    "block_database": 65536,
    "margin": None,
}

_IVF = {"nlist": None, "nprobe": 16, "seed": 1234}
IVF_FLAT = dict(_IVF)
IVF_PQ = {**_IVF, "m": None, "nbits": 8}
HNSW = {"M": 32, "ef_search": 128, "ef_construction": 200}
