"""The toy pipeline (toy_pipeline.py), run once a process for every stage test that reads
it: the tests only read its stores, and a worker of pytest-xdist taking several of these
modules builds it once, as the one module they came from (test_stages.py) did."""

from __future__ import annotations

import pytest
from synthetic import make_dataset
from toy_pipeline import METHODS, N_PLACES, SCHEMA, Runner
from workflow_helpers import toy_config

from vprflow.planning.config import validate_config
from vprflow.planning.plan import build_plan


@pytest.fixture(scope="session")
def pipeline(tmp_path_factory):
    root = tmp_path_factory.mktemp("stages")
    make_dataset(root / "data" / "toy", n_places=N_PLACES, width=64, height=48)
    config = toy_config(
        root / "data",
        resolution=[64, 48],
        recall_at=[1, 3],
        methods=METHODS,
        defaults={"pca": {"dim": 8, "whiten": False}, "segvlad": {"order": 1}},
        rerank={"anyloc_vlad": ["mnn"], "segvlad": ["ransac"]},
    )
    config["rerankers"] = {
        "mnn": {"kind": "mnn", "features": "daisy", "top_k": 4},
        "ransac": {"kind": "ransac", "features": "daisy", "min_similarity": 0.5},
    }
    config["vocabulary"].update(n_clusters=3, n_iter=5)
    config["segmenters"]["slic"].update(n_segments=6, resolution_scale=1.0)
    config = validate_config(config, SCHEMA)
    plan = build_plan(config)
    runner = Runner(plan, root / "data", root / "cache")
    recalls = [runner.path("recall", run.recall_key) for run in plan.runs["toy"]]
    return plan, runner, recalls, root
