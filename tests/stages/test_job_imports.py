"""A job imports only the heavy libraries it computes with: torch costs ~1.2 s a process,
faiss, cv2 and scikit-image a tenth of that each, paid by every job of a stage.

Each stage's jobs of a toy plan (the five aggregator families, both re-rankers) run again
in a fresh process, as the rules' script runs them (``run_job``; a gather's
``combine_shards``), which then lists the heavy libraries in its ``sys.modules``."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import asdict, replace

import pytest
from synthetic import make_dataset
from workflow_helpers import SCHEMA, run_stage, toy_config

from vprflow.planning.config import validate_config
from vprflow.planning.plan import STAGES, build_plan
from vprflow.stages.jobs import Job, run_job, shard_ranges

HEAVY = ("torch", "transformers", "faiss", "cv2", "matplotlib", "skimage", "sklearn")
METHODS = ["anyloc_vlad", "segvlad", "segment_gem", "snsm", "gem"]
RERANK = {"anyloc_vlad": ["mnn", "ransac"], "segvlad": ["mnn", "ransac"]}

# What each stage's jobs compute with, of HEAVY, on the CPU (DAISY features and SLIC
# segments: scikit-image). The PCA and descriptors of a VLAD method (the published
# assignment) and the matches (mutual nearest neighbours) compute with torch: their rows
# are below, and every other job of theirs computes with none of HEAVY.
COMPUTES_WITH = {
    "images": set(),
    "dataset": set(),
    "features": {"skimage"},
    "segments": {"skimage"},
    "vocabulary": {"faiss"},  # faiss's start; DAISY's vocabulary is given no device
    "search": {"faiss"},  # the published flat search
    "recall": {"faiss"},  # a global method's flat search
    "rerank": {"cv2"},  # RANSAC's homography
    "gather": set(),
}

CHILD = """
import json, sys
from vprflow.stages.jobs import Job, combine_shards, run_job

for entry in json.loads(sys.argv[1]):
    if "shards" in entry:
        combine_shards(entry["shards"], entry["record"], entry["out"])
    else:
        run_job(Job(**entry))
print(json.dumps(sorted(name for name in {heavy!r} if name in sys.modules)))
"""


@pytest.fixture(scope="module")
def toy_jobs(tmp_path_factory) -> dict[str, list[dict]]:
    """Per stage, its jobs of the toy plan (run once here, in this process) as the
    keyword arguments of a :class:`Job` whose output is a new path; ``gather``: the
    features' shards to combine."""
    root = tmp_path_factory.mktemp("imports")
    make_dataset(root / "data" / "toy", n_places=6)
    config = toy_config(root / "data", methods=METHODS, rerank=RERANK)
    plan = build_plan(validate_config(config, SCHEMA))
    done: dict = {}
    jobs: dict[str, list[dict]] = {}
    for stage, stages in plan.stages.items():
        for key, planned in stages.items():
            run_stage(plan, stage, key, root / "data", root / "stores", done)
            inputs = {n: done[ref] for n, ref in planned.inputs.items()}
            job = Job(
                planned.record,
                inputs,
                str(root / "again" / stage / f"{key}.zarr"),
                data_root=str(root / "data"),
                run=planned.run_params,  # as the rules pass them: device auto
            )
            jobs.setdefault(stage, []).append(asdict(job))
    features = Job(**jobs["features"][0])
    sizes = {"shard_size": 4, "descriptors_shard_size": 4, "search_shard_size": 4}
    shards = []
    for start, stop in shard_ranges("features", 6, 6, sizes):
        shards.append(str(root / "shards" / f"{start}-{stop}.zarr"))
        run_job(replace(features, out=shards[-1], start=start, stop=stop))
    gathered = str(root / "again" / "gather.zarr")
    jobs["gather"] = [{"shards": shards, "record": features.record, "out": gathered}]
    return jobs


def imported(jobs: list[dict]) -> set[str]:
    """The libraries of HEAVY a fresh process holds after running ``jobs``."""
    result = subprocess.run(
        [sys.executable, "-c", CHILD.format(heavy=HEAVY), json.dumps(jobs)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return set(json.loads(result.stdout.splitlines()[-1]))


def test_the_toy_plan_has_every_stage_the_rules_run(toy_jobs):
    # A stage missing from the plan would leave its test below asserting nothing.
    assert set(STAGES) | {"gather"} == set(toy_jobs)


@pytest.mark.parametrize("stage", sorted(COMPUTES_WITH))
def test_a_stage_job_imports_no_heavy_library_it_does_not_compute_with(toy_jobs, stage):
    found = imported(toy_jobs[stage])
    assert "torch" not in found, f"a {stage} job imported torch"
    assert found <= COMPUTES_WITH[stage], f"{stage}: {sorted(found)}"


@pytest.mark.parametrize("stage", ["pca", "descriptors"])
def test_the_pca_and_descriptors_of_a_method_without_a_vocabulary_import_no_torch(toy_jobs, stage):
    """Only VLAD assigns patches with torch (the published assignment): SNSM, GeM and
    per-segment GeM compute in numpy."""
    jobs = [job for job in toy_jobs[stage] if "vocabulary" not in job["inputs"]]
    assert jobs, stage
    assert "torch" not in imported(jobs)


@pytest.mark.parametrize("stage", ["pca", "descriptors", "matches"])
def test_each_stage_that_computes_with_torch_imports_it(toy_jobs, stage):
    """The counterpart: the same child sees torch where a job computes with it, so an
    empty set above is the stage's, not a child that imports nothing."""
    jobs = [job for job in toy_jobs[stage] if stage == "matches" or "vocabulary" in job["inputs"]]
    assert jobs, stage
    assert all("torch" in imported([job]) for job in jobs)


def test_the_rules_scripts_import_neither_the_planner_nor_a_stage_before_a_job_runs():
    """What ``workflow/scripts/stage.py`` and ``gather.py`` import before their job: the
    runners, not the planner (~50 ms a job) nor any stage's module."""
    code = (
        "import sys, vprflow.stages.jobs, vprflow.stages.runner; "
        "print(sorted(m for m in sys.modules if m.startswith(('vprflow.planning', "
        "'vprflow.stages.')) and m not in ('vprflow.stages.base', 'vprflow.stages.jobs', "
        "'vprflow.stages.runner')))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"
