"""How a job of any stage runs, and the sharding policy the rules, tests and benchmarks
share, all read from the plan's table of stages."""

from __future__ import annotations

import ast
import importlib
import inspect
import textwrap

import pytest

from vprflow.planning.plan import STAGES
from vprflow.stages import jobs
from vprflow.stages.base import Job as BaseJob
from vprflow.stages.jobs import Job, combine_shards, run_job, shard_ranges


def _runner_function(stage: str):
    """The stage function a runner of ``jobs.RUNNERS`` imports and calls."""
    source = inspect.getsource(jobs.RUNNERS[stage])
    found = ast.parse(textwrap.dedent(source)).body[0].body[0]
    assert isinstance(found, ast.ImportFrom), source
    module = importlib.import_module(found.module)
    return module, getattr(module, found.names[0].name)


def test_every_stage_of_the_plan_has_a_runner():
    assert list(jobs.RUNNERS) == list(STAGES)
    assert jobs.SHARDED == ("features", "segments", "descriptors", "search")
    assert Job is BaseJob


@pytest.mark.parametrize("stage", sorted(STAGES))
def test_every_stage_runs_by_one_function_of_one_job_in_its_stage_module(stage):
    """Each runner calls one function of a stages/ module that takes the job alone: no
    stage needs an adapter between the rules' script and its function."""
    module, function = _runner_function(stage)
    assert module.__name__.startswith("vprflow.stages.")
    assert list(inspect.signature(function).parameters) == ["job"], function


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


SEEN: list[Job] = []


def _record_job(job: Job) -> None:
    SEEN.append(job)


def test_a_job_runs_the_runner_its_record_names(monkeypatch):
    SEEN.clear()
    monkeypatch.setitem(jobs.RUNNERS, "pca", _record_job)
    job = Job({"stage": "pca", "params": {}}, {"images": "d.zarr"}, "out.zarr")
    run_job(job)
    assert SEEN == [job]
    assert (job.device, job.batch_size) == ("auto", 1)


def test_a_jobs_images_are_its_range_within_the_stores_images():
    job = Job({"stage": "features", "params": {}}, {}, "o.zarr")
    assert job.images(5) == range(5)
    assert Job(job.record, {}, "o.zarr", start=2, stop=9).images(5) == range(2, 5)


def test_search_shards_are_merged_and_other_shards_concatenated(monkeypatch):
    import vprflow.stages.gather as gather_module
    import vprflow.stages.search as search_module

    calls = []
    monkeypatch.setattr(gather_module, "gather", lambda *a: calls.append(("gather", *a)))
    monkeypatch.setattr(search_module, "merge_search", lambda *a: calls.append(("merge", *a)))
    combine_shards(["a", "b"], {"stage": "search"}, "o")
    combine_shards(["a"], {"stage": "features"}, "o")
    assert [call[0] for call in calls] == ["merge", "gather"]
