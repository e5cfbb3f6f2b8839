"""The segment search stage (vprflow.stages.search): sharded, flat and other indexes."""

from __future__ import annotations

import numpy as np
import pytest
from toy_pipeline import N_PLACES, stage_path

from vprflow.core import stores
from vprflow.stages.jobs import Job
from vprflow.stages.readers import read_search
from vprflow.stages.recall import compute_recall
from vprflow.stages.search import compute_search


def test_sharded_search_equals_one_faiss_search_over_all_references(pipeline):
    """Three reference shards merged give the lists of one exact search (ties by index)."""
    from vprflow.search.flat import flat_knn

    group = stores.open_store(stage_path(pipeline, "descriptors"))
    offsets = np.asarray(group["descriptors_offsets"][...])
    split = int(offsets[N_PLACES])
    vectors = np.asarray(group["descriptors"][...])
    distances, indices = read_search(stage_path(pipeline, "search"))
    expected_d, expected_i = flat_knn(vectors[:split], vectors[split:], 50)
    np.testing.assert_array_equal(distances, expected_d)
    np.testing.assert_array_equal(indices, expected_i)
    # Against float64: every list holds the true nearest segments.
    exact = ((vectors[split:, None, :].astype(np.float64) - vectors[None, :split]) ** 2).sum(-1)
    k = indices.shape[1]
    for row in range(len(exact)):
        kth = np.sort(exact[row])[k - 1]
        assert (exact[row, indices[row]] <= kth + 1e-4).all()


@pytest.mark.parametrize(
    ("index", "options"),
    [("exact_fast", {"block_database": 40}), ("ivf_flat", {"nlist": 4, "nprobe": 4})],
)
def test_other_indexes_search_the_same_descriptors(pipeline, tmp_path, index, options):
    """exact_fast gives the flat lists (float32 re-scored distances); an IVF index that
    probes every list is exhaustive too; with an approximate index, recall also reports
    the exact search's Recall@N, which equals the flat method's."""
    plan, runner, _, _ = pipeline
    (search,) = [
        s
        for s in plan.stages["search"].values()
        if runner.path(*s.inputs["descriptors"]) == stage_path(pipeline, "descriptors", "segvlad")
    ]
    inputs = {name: runner.path(*ref) for name, ref in search.inputs.items()}
    spec = {**search.record["params"], "index": index, "params": options}
    out = str(tmp_path / "search.zarr")
    compute_search(Job({**search.record, "params": spec}, inputs, out))
    distances, indices = read_search(out)
    flat_distances, flat_indices = read_search(stage_path(pipeline, "search"))
    np.testing.assert_array_equal(indices, flat_indices)
    np.testing.assert_allclose(distances, flat_distances, rtol=1e-5, atol=1e-5)
    (recall,) = [
        s
        for s in plan.stages["recall"].values()
        if s.inputs.get("search") == ("search", search.key) and "rerank" not in s.inputs
    ]
    result = str(tmp_path / "recall.zarr")
    dataset = stage_path(pipeline, "dataset")
    both = {"search": out, "exact_search": out}
    compute_recall(
        Job(
            recall.record,
            {"dataset": dataset, "descriptors": inputs["descriptors"], **both},
            result,
        )
    )
    attrs = stores.open_store(result).attrs
    flat = stores.open_store(stage_path(pipeline, "recall", "segvlad")).attrs
    assert attrs["recall_exact"] == attrs["recall"] == flat["recall"]
