"""Run a small workflow through a real local SLURM scheduler (sbatch/srun) with the
repository's SLURM profile, and compare it with a local run.

Needs root and the Debian SLURM packages (scripts/install_slurm.sh); skipped otherwise,
failed under CI=true. Takes about a minute.
"""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path

import pytest
from slurm_fixtures import (
    REPO,
    run_snakemake,
    slurm_job_info,
    snakemake_slurm_command,
    submitted_job_ids,
)

pytestmark = pytest.mark.slurm

# Rule names `features` and `segments` match the profile's GPU rules, so the profile's
# set-resources (and the test's GPU stripping) are exercised too.
TOY_SNAKEFILE = textwrap.dedent(
    """
    SAMPLES = ["a", "b"]

    rule all:
        input:
            "results/summary.txt",

    rule features:
        output:
            "results/features/{s}.txt",
        log:
            "logs/features/{s}.log",
        resources:
            runtime=5,
        shell:
            "python -c 'import sys; print(sum(ord(c) * i for i, c in enumerate(sys.argv[1] * 50)))'"
            " {wildcards.s} > {output} 2> {log}"

    rule segments:
        input:
            "results/features/{s}.txt",
        output:
            "results/segments/{s}.txt",
        log:
            "logs/segments/{s}.log",
        threads: 1
        shell:
            "(echo {wildcards.s}; cat {input}; echo threads={threads}) > {output} 2> {log}"

    rule summary:
        input:
            expand("results/segments/{s}.txt", s=SAMPLES),
        output:
            "results/summary.txt",
        log:
            "logs/summary.log",
        resources:
            mem_mb=500,
        run:
            with open(log[0], "w") as lf, open(output[0], "w") as out:
                for path in input:
                    out.write(open(path).read())
                    print("read", path, file=lf)
    """
)

OUTPUTS = [
    "results/features/a.txt",
    "results/features/b.txt",
    "results/segments/a.txt",
    "results/segments/b.txt",
    "results/summary.txt",
]


def _write_workflow(directory: Path) -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    snakefile = directory / "Snakefile"
    snakefile.write_text(TOY_SNAKEFILE)
    return snakefile


def test_toy_workflow_through_sbatch_matches_local_run(slurm_cluster, tmp_path):
    local_dir, slurm_dir = tmp_path / "local", tmp_path / "slurm"

    # reference: plain local run with the repository's local profile
    local_snakefile = _write_workflow(local_dir)
    local_cmd = [
        sys.executable, "-m", "snakemake",
        "--snakefile", str(local_snakefile),
        "--directory", str(local_dir),
        "--profile", str(REPO / "workflow" / "profiles" / "default"),
        "--cores", "2",
    ]  # fmt: skip
    local_out, local_seconds = run_snakemake(local_cmd, cwd=local_dir)

    slurm_snakefile = _write_workflow(slurm_dir)
    cmd = snakemake_slurm_command(slurm_cluster, slurm_snakefile, slurm_dir)
    out, slurm_seconds = run_snakemake(cmd, cwd=slurm_dir)
    print(f"toy workflow: local {local_seconds:.1f} s, SLURM {slurm_seconds:.1f} s")

    # every output exists and equals the local run's
    for rel in OUTPUTS:
        assert (slurm_dir / rel).is_file(), f"missing {rel}\n{out[-4000:]}"
        assert (slurm_dir / rel).read_bytes() == (local_dir / rel).read_bytes(), rel
    assert (slurm_dir / "logs" / "summary.log").read_text().count("read ") == 2

    # 5 jobs (2 features, 2 segments, 1 summary) went through sbatch
    job_ids = submitted_job_ids(out)
    assert len(job_ids) == 5, out[-4000:]
    assert len(set(job_ids)) == 5
    slurm_logs = sorted((slurm_dir / ".snakemake" / "slurm_logs").rglob("*.log"))
    assert {int(p.stem) for p in slurm_logs} == set(job_ids), slurm_logs

    # SLURM ran them to completion with the profile's resources (fitted to the node)
    info = slurm_job_info(job_ids)
    for job_id, fields in info.items():
        assert fields.get("JobState") == "COMPLETED", (job_id, fields)
        assert fields.get("Partition") == slurm_cluster.partition
        # the profile's `gpu: 1` was stripped for this GPU-less cluster
        assert not any("gpu" in value.lower() for value in fields.values()), fields
    by_rule = {}
    for path in slurm_logs:
        rule = path.relative_to(slurm_dir / ".snakemake" / "slurm_logs").parts[0]
        by_rule.setdefault(rule.removeprefix("rule_"), []).append(int(path.stem))
    assert sorted(by_rule) == ["features", "segments", "summary"], by_rule
    mem_cap = slurm_cluster.real_memory_mb // slurm_cluster.cpus
    for job_id in by_rule["features"]:
        # profile: features mem_mb = 16000 * attempt, capped to the node's share
        assert info[job_id]["MinMemoryNode"] == f"{min(16000, mem_cap)}M", info[job_id]
        # profile: features runtime = 120 * attempt minutes; set-resources beats the
        # rule's own `runtime=5`
        assert info[job_id]["TimeLimit"] == "02:00:00", info[job_id]
    for job_id in by_rule["summary"]:
        assert info[job_id]["MinMemoryNode"] == "500M", info[job_id]  # rule's own resources
        assert info[job_id]["TimeLimit"] == "01:00:00", info[job_id]  # profile default 60 min
