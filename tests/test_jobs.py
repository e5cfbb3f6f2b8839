"""The table of stage runners and the sharding policy the rules, tests and benchmarks
share."""

from __future__ import annotations

import pytest

from vprflow.planning.plan import FORMAT_VERSIONS
from vprflow.stages.jobs import RUNNERS, SHARDED, Job, combine_shards, run_job, shard_ranges


def test_every_stage_the_plan_makes_has_a_runner_and_every_sharded_stage_is_one():
    assert set(RUNNERS) == set(FORMAT_VERSIONS)
    assert set(SHARDED) <= set(RUNNERS)


@pytest.mark.parametrize("size", [1, 3, 4, 7, 100])
def test_per_image_shards_cover_references_then_queries_once_in_order(size):
    ranges = shard_ranges(
        "features", n_reference=4, n_query=3, shard_size=size, search_shard_size=2
    )
    covered = [i for start, stop in ranges for i in range(start, stop)]
    assert covered == list(range(7))
    assert all(0 < stop - start <= size for start, stop in ranges)


def test_search_shards_cover_the_reference_images_only():
    ranges = shard_ranges("search", n_reference=5, n_query=9, shard_size=1, search_shard_size=2)
    assert ranges == [(0, 2), (2, 4), (4, 5)]


def test_a_shard_size_of_zero_is_one_job():
    assert shard_ranges("segments", 4, 3, shard_size=0, search_shard_size=0) == [(0, 7)]
    assert shard_ranges("search", 4, 3, shard_size=0, search_shard_size=0) == [(0, 4)]


def test_an_unsharded_stage_has_no_shard_ranges():
    with pytest.raises(ValueError, match="'recall' is not sharded"):
        shard_ranges("recall", 4, 3, 2, 2)


def test_a_job_runs_the_runner_its_record_names(monkeypatch):
    seen = []
    monkeypatch.setitem(RUNNERS, "pca", seen.append)
    job = Job({"stage": "pca", "params": {}}, {"images": "d.zarr"}, "out.zarr")
    run_job(job)
    assert seen == [job]
    assert (job.device, job.batch_size) == ("auto", 1)


def test_search_shards_are_merged_and_other_shards_concatenated(monkeypatch):
    import vprflow.stages.gather as gather_module
    import vprflow.stages.search as search_module

    calls = []
    monkeypatch.setattr(gather_module, "gather", lambda *a: calls.append(("gather", *a)))
    monkeypatch.setattr(search_module, "merge_search", lambda *a: calls.append(("merge", *a)))
    combine_shards(["a", "b"], {"stage": "search"}, "o")
    combine_shards(["a"], {"stage": "features"}, "o")
    assert [call[0] for call in calls] == ["merge", "gather"]
