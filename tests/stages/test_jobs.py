"""How a job of any stage runs, and the sharding policy the rules, tests and benchmarks
share, all read from the plan's table of stages."""

from __future__ import annotations

import ast
import importlib
import inspect
import textwrap
from pathlib import Path

import pytest
import yaml

from vprflow.planning.config import validate_config
from vprflow.planning.plan import SHARDED, STAGES
from vprflow.stages import jobs
from vprflow.stages.base import Job as BaseJob
from vprflow.stages.jobs import Job, combine_shards, run_job, shard_ranges

REPO = Path(__file__).resolve().parents[2]
SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"


def _runner_function(stage: str):
    """The stage function a runner of ``jobs.RUNNERS`` calls: ``<module>.<function>(job)``,
    the module one of jobs.py's lazy imports."""
    source = inspect.getsource(jobs.RUNNERS[stage])
    (found,) = ast.parse(textwrap.dedent(source)).body[0].body
    call = found.value
    assert isinstance(call, ast.Call) and isinstance(call.func, ast.Attribute), source
    module = importlib.import_module(getattr(jobs, call.func.value.id).__name__)
    return module, getattr(module, call.func.attr)


def test_every_stage_of_the_plan_has_a_runner():
    assert list(jobs.RUNNERS) == list(STAGES)
    assert SHARDED == ("features", "segments", "descriptors", "search")
    assert Job is BaseJob


@pytest.mark.parametrize("stage", sorted(STAGES))
def test_every_stage_runs_by_one_function_of_one_job_in_its_stage_module(stage):
    """Each runner calls one function of a stages/ module that takes the job alone: no
    stage needs an adapter between the rules' script and its function."""
    module, function = _runner_function(stage)
    assert module.__name__.startswith("vprflow.stages.")
    assert list(inspect.signature(function).parameters) == ["job"], function


def _sizes(shard_size: int = 0, descriptors: int = 0, search: int = 0) -> dict[str, int]:
    return {
        "shard_size": shard_size,
        "descriptors_shard_size": descriptors,
        "search_shard_size": search,
    }


@pytest.mark.parametrize("size", [1, 3, 4, 7, 100])
def test_per_image_shards_cover_references_then_queries_once_in_order(size):
    ranges = shard_ranges("features", n_reference=4, n_query=3, sizes=_sizes(size, 2, 2))
    covered = [i for start, stop in ranges for i in range(start, stop)]
    assert covered == list(range(7))
    assert all(0 < stop - start <= size for start, stop in ranges)


def test_search_shards_cover_the_reference_images_only():
    ranges = shard_ranges("search", n_reference=5, n_query=9, sizes=_sizes(1, 1, 2))
    assert ranges == [(0, 2), (2, 4), (4, 5)]


def test_descriptors_shards_take_their_own_size_over_every_image():
    sizes = _sizes(shard_size=2, descriptors=4, search=1)
    assert shard_ranges("descriptors", 5, 4, sizes) == [(0, 4), (4, 8), (8, 9)]
    assert shard_ranges("features", 5, 4, sizes) == [(0, 2), (2, 4), (4, 6), (6, 8), (8, 9)]
    assert shard_ranges("segments", 5, 4, sizes) == shard_ranges("features", 5, 4, sizes)


def test_descriptors_shards_of_the_schema_default_are_one_job_up_to_4000_images():
    shipped = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config = validate_config(
        {key: value for key, value in shipped.items() if not key.endswith("shard_size")}, SCHEMA
    )
    assert config["descriptors_shard_size"] == 4000
    assert shard_ranges("descriptors", 2000, 2000, config) == [(0, 4000)]
    assert shard_ranges("descriptors", 2000, 2001, config) == [(0, 4000), (4000, 4001)]
    # The model stages' size stays the schema's own (one job), unaffected.
    assert shard_ranges("features", 2000, 2001, config) == [(0, 4001)]


@pytest.mark.parametrize("stage", ["features", "segments", "descriptors", "search"])
def test_a_shard_size_of_zero_is_one_job(stage):
    n_images = 4 if stage == "search" else 7
    assert shard_ranges(stage, 4, 3, _sizes()) == [(0, n_images)]


def test_every_sharded_stage_names_a_shard_size_key_of_the_schema():
    schema = yaml.safe_load(SCHEMA.read_text())
    for stage in SHARDED:
        key = STAGES[stage].shard_size
        assert schema["properties"][key]["type"] == "integer", stage
    assert all(STAGES[stage].shard_size is None for stage in STAGES if stage not in SHARDED)


def test_an_unsharded_stage_has_no_shard_ranges():
    with pytest.raises(ValueError, match="'recall' is not sharded"):
        shard_ranges("recall", 4, 3, _sizes(2, 2, 2))


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
