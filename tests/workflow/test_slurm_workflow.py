"""The real vprflow workflow through a real local SLURM scheduler, sharded, compared
with the same stages run locally. Needs root and scripts/install_slurm.sh; fails under CI=true
when SLURM cannot start."""

from __future__ import annotations

import pytest
from slurm_fixtures import (
    run_snakemake,
    slurm_job_info,
    snakemake_slurm_command,
    submitted_job_ids,
)
from synthetic import make_dataset
from workflow_helpers import SNAKEFILE, table_in_process, toy_config, untimed_table, write_config

pytestmark = pytest.mark.slurm
TARGET = "results/recall_toy.csv"


def test_sharded_workflow_on_slurm_matches_local_run(slurm_cluster, tmp_path):
    local_dir, cluster_dir = tmp_path / "local", tmp_path / "cluster"
    for workdir in (local_dir, cluster_dir):
        make_dataset(workdir / "data" / "toy")
    # A per-segment method: every kind of sharded job (per-image shards and their gather,
    # reference shards of the segment search and their merge). The other sharded paths
    # (descriptors' shards, a global method, three search shards) are the same rules'
    # and are compared bit for bit with an unsharded run locally (test_workflow.py); each
    # cluster job costs ~4 CPU s here (a Snakemake process parsing the workflow, then
    # the stage's), so this run keeps one of each.
    config = toy_config(local_dir / "data", methods=["segvlad_o0_nopca"])
    # The local table through the same stages, unsharded, in this process.
    local_table = table_in_process(config, local_dir, "toy")

    config["data_root"] = str(cluster_dir / "data")
    config["shard_size"] = 10  # 20 images -> 2 shards per per-image stage
    config["descriptors_shard_size"] = 0  # one descriptors shard
    config["search_shard_size"] = 5  # 10 references -> 2 segment-search jobs, merged
    config_path = write_config(cluster_dir, config)
    command = snakemake_slurm_command(
        slurm_cluster, SNAKEFILE, cluster_dir, TARGET, "--configfile", str(config_path)
    )
    output, seconds = run_snakemake(command, cwd=cluster_dir)

    job_ids = submitted_job_ids(output)
    # images, dataset (the ground truth), 2 feature shards + gather, 2 segment shards +
    # gather, vocabulary, descriptors in one shard + its gather (a rename), 2 search
    # shards + merge, recall; the tables and the report run locally.
    assert len(job_ids) == 15, output[-3000:]
    states = {fields.get("JobState") for fields in slurm_job_info(job_ids).values()}
    assert states == {"COMPLETED"}
    logs = list((cluster_dir / ".snakemake" / "slurm_logs").rglob("*.log"))
    assert {int(p.stem) for p in logs} >= set(job_ids)
    # Each segment-search shard was its own cluster job.
    search_jobs = {p.stem for p in logs if p.relative_to(cluster_dir).parts[2] == "rule_search"}
    assert len(search_jobs) == 2, sorted(str(p) for p in logs)
    # Byte for byte but the milliseconds a query, which time each run's stores.
    assert untimed_table(cluster_dir / TARGET) == untimed_table(local_table)
    print(f"SLURM run: {len(job_ids)} jobs in {seconds:.0f} s")
