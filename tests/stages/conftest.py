"""The toy pipeline (toy_pipeline.py), run once a process for every stage test that reads
it: the tests only read its stores, and a worker of pytest-xdist taking several of these
modules builds it once, as the one module they came from (test_stages.py) did."""

from __future__ import annotations

import pytest
from synthetic import make_dataset
from toy_pipeline import N_PLACES, Runner, pipeline_config

from vprflow.planning.plan import build_plan


@pytest.fixture(scope="session")
def pipeline(tmp_path_factory):
    root = tmp_path_factory.mktemp("stages")
    make_dataset(root / "data" / "toy", n_places=N_PLACES, width=64, height=48)
    plan = build_plan(pipeline_config(root / "data"))
    runner = Runner(plan, root / "data", root / "cache")
    recalls = [runner.path("recall", run.recall_key) for run in plan.runs["toy"]]
    return plan, runner, recalls, root
