"""Checks and conversions of the k-NN searches' arguments, shared by :mod:`vprflow.search`'s
modules."""

from __future__ import annotations

from typing import Any

import numpy as np


def as_matrix(array: Any, name: str) -> np.ndarray:
    # np.asarray keeps memory maps as they are; blocks are converted to float32 one at a time.
    array = np.asarray(array)
    if array.ndim != 2:
        raise ValueError(f"{name} must be a [N, D] matrix, got shape {array.shape}")
    return array


def faiss_inputs(database: Any, queries: Any, k: Any) -> tuple[np.ndarray, np.ndarray, int]:
    """``(database, queries, k')`` as faiss takes them: contiguous float32 ``[N, D]``
    matrices of one dimension, ``k' = min(k, Nd)``."""
    database = np.ascontiguousarray(as_matrix(database, "database"), dtype=np.float32)
    queries = np.ascontiguousarray(as_matrix(queries, "queries"), dtype=np.float32)
    n_db, dim = database.shape
    if queries.shape[1] != dim:
        raise ValueError(f"database has dimension {dim} but queries {queries.shape[1]}")
    return database, queries, min(non_negative_int("k", k), n_db)


def empty_result(n_queries: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``(distances, indices)`` of a search with nothing to find (``k`` or
    ``n_queries`` 0)."""
    return np.zeros((n_queries, k), np.float32), np.zeros((n_queries, k), np.int64)


def positive_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def non_negative_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise ValueError(f"{name} must be a non-negative integer, got {value!r}")
    return int(value)
