"""The toy pipeline the stage tests read: every stage function run directly, without
Snakemake, on a synthetic dataset with the weight-free DAISY features and SLIC segments
(the ``pipeline`` fixture, tests/stages/conftest.py), and the stores of one method's
stages in it."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from synthetic import make_dataset
from workflow_helpers import toy_config

from vprflow.core import stores
from vprflow.planning.config import validate_config
from vprflow.planning.plan import SHARDED, build_plan
from vprflow.stages.jobs import Job, combine_shards, run_job, shard_ranges
from vprflow.stages.readers import Dataset

REPO = Path(__file__).resolve().parents[2]
SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"
METHODS = ["anyloc_vlad", "segvlad", "gem", "snsm", "segment_gem"]
N_PLACES = 6


def pipeline_config(data_root: Path, **segmenter) -> dict:
    """The toy pipeline's validated config over ``data_root`` (holding ``toy``), its SLIC
    entry updated with ``segmenter``."""
    config = toy_config(
        data_root,
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
    config["segmenters"]["slic"].update(n_segments=6, resolution_scale=1.0, **segmenter)
    return validate_config(config, SCHEMA)


class Runner:
    """Runs a plan's stages in dependency order through the rules' own table
    (:mod:`vprflow.stages.jobs`): per-image stages in two shards (references, queries),
    the segment search in uneven shards of 4 references, then combined; segments in
    batches of 4 (a ragged last batch in each shard)."""

    # The top-level config's shard sizes: every per-image stage in shards of N_PLACES.
    SHARD_SIZES = {"shard_size": N_PLACES, "descriptors_shard_size": N_PLACES}
    SHARD_SIZES["search_shard_size"] = 4

    def __init__(self, plan, data_root: Path, out: Path):
        self.plan, self.data_root, self.out = plan, str(data_root), out
        self.done: dict[tuple[str, str], str] = {}

    def path(self, stage: str, key: str) -> str:
        if (stage, key) not in self.done:
            self.done[stage, key] = self._run(self.plan.get(stage, key))
        return self.done[stage, key]

    def _run(self, stage) -> str:
        inputs = {name: self.path(*ref) for name, ref in stage.inputs.items()}
        out = str(self.out / stage.stage / f"{stage.key}.zarr")
        job = Job(
            stage.record,
            inputs,
            out,
            data_root=self.data_root,
            run={"device": "cpu", "batch_size": 4},
            threads=2,
        )
        if stage.stage not in SHARDED:
            run_job(job)
            return out
        dataset = Dataset(inputs["images"])
        ranges = shard_ranges(stage.stage, dataset.n_reference, dataset.n_query, self.SHARD_SIZES)
        shards = [f"{out}.shards/{start}-{stop}.zarr" for start, stop in ranges]
        for (start, stop), shard in zip(ranges, shards, strict=True):
            run_job(replace(job, out=shard, start=start, stop=stop))
        combine_shards(shards, stage.record, out)
        return out


def stage_path(pipeline, stage: str, method: str = "segvlad") -> str:
    plan, runner, _, _ = pipeline
    run = {r.method: r for r in plan.runs["toy"]}[method]
    users = {}
    from vprflow.planning.store_index import stage_users

    for (name, key), rows in stage_users(plan).items():
        if name == stage and ("toy", method) in rows:
            users[key] = runner.path(name, key)
    assert len(users) == 1, (stage, method, run)
    return next(iter(users.values()))


def rerank_store(pipeline, method: str):
    plan, runner, _, _ = pipeline
    run = {r.method: r for r in plan.runs["toy"]}[method]
    return stores.open_store(runner.path(*plan.get("recall", run.recall_key).inputs["rerank"]))


def small_plan(root: Path, memo: dict | None = None, make: bool = True):
    """A validated plan of one global method on a 3-place toy dataset (made fresh)."""
    if make:
        make_dataset(root / "data" / "toy", n_places=3, width=32, height=24)
    config = toy_config(root / "data", resolution=[32, 24], methods=["gem"])
    return build_plan(validate_config(config, SCHEMA), memo)
