"""The SLURM profile with partition, account, GPU type and CPUs named on the command
line, the way docs/cluster.md shows it.

Snakemake turns each profile key into the command-line option of that name unless the
option is on the command line already, and the resource options take any number of
values. So a target after ``--default-resources slurm_partition=gpu`` is parsed as a
resource (a crash), and a command-line ``--default-resources`` / ``--set-resources``
replaces the profile's whole key; the rules carry their own memory and time so that
nothing else is lost. Here:

* every command line of the docs' "on the command line" section runs as a dry run of the
  real workflow (``--executor slurm -n`` needs no cluster) and gives every job the
  partition, account, GPU type or CPUs the docs promise, while each rule keeps its own
  memory and time;
* a target written after such an option still fails with the error the docs quote;
* one real submission to the local SLURM (``slurm_cluster``) with a partition and account
  for all jobs, a GPU partition and GPU type for ``features`` and fewer threads for it:
  what ``sbatch`` received and what SLURM ran.

Needs the SLURM executor plugin; the real submission also needs root and
scripts/install_slurm.sh (skipped otherwise, failed under CI=true). About a minute.
"""

from __future__ import annotations

import importlib.util
import os
import re
import shlex
import sys
from pathlib import Path

import pytest
from slurm_fixtures import (
    REPO,
    SLURM_PROFILE,
    cluster_limits,
    extra_partition,
    gpu_stripping_wrappers,
    node_memory_share_mb,
    run_snakemake,
    slurm_environment,
    slurm_job_info,
    submitted_job_ids,
    wrapped_calls,
)
from synthetic import make_dataset
from workflow_helpers import SNAKEFILE, dry_run, toy_config, write_config

if importlib.util.find_spec("snakemake_executor_plugin_slurm") is None:
    _reason = 'the SLURM executor is an extra: pip install -e ".[slurm]"'
    if os.environ.get("CI", "").lower() in {"1", "true", "yes"}:
        pytest.fail(f"CI=true but the SLURM tests cannot run: {_reason}", pytrace=False)
    pytest.skip(_reason, allow_module_level=True)
pytestmark = pytest.mark.slurm

DOCS = REPO / "docs" / "cluster.md"
SECTION = "## Partition, account, GPU type and CPUs on the command line"
DATASET = "17places"  # the dataset the docs' command lines name
TARGET = f"results/recall_{DATASET}.csv"
# Rules that run on the submitting machine (`localrules:` / the default target).
LOCAL_RULES = {"recall_csv", "all"}
# Memory (MB) and time (min) that each rule sets in its own `resources:`, at attempt 1
# (workflow/rules/*.smk). A command-line --default-resources / --set-resources must not
# take them away.
OWN_RESOURCES = {
    "images": (4000, 60),
    "dataset": (4000, 60),
    "features": (16000, 120),
    "gather": (4000, 60),
    "segments": (16000, 180),
    "vocabulary": (4000, 60),
    "pca": (4000, 60),
    "descriptors": (4000, 60),
}
ABSENT = None
GPU = {"slurm_partition": "gpu", "gpu_model": "a100", "gpu": "1"}
# What the jobs of each documented command line get, by the comment above it in the
# docs: rule -> {resource: value, or ABSENT}; "*" = every other cluster rule.
EXPECTED = {
    "partition for every job": {
        "*": {"slurm_partition": "cpu", "slurm_account": ABSENT, "gpu_model": ABSENT},
    },
    "partition and account for every job": {
        "*": {"slurm_partition": "cpu", "slurm_account": "my_project"},
    },
    "GPU partition and GPU type for the model stages only": {
        "features": GPU,
        "segments": GPU,
        "*": {"slurm_partition": ABSENT, "gpu_model": ABSENT, "slurm_account": ABSENT},
    },
    "all of the above, with the targets after --": {
        "features": {**GPU, "slurm_account": "my_project"},
        "segments": {**GPU, "slurm_account": "my_project"},
        "*": {"slurm_partition": "cpu", "slurm_account": "my_project", "gpu_model": ABSENT},
    },
    "CPUs of one rule: its threads and sbatch --cpus-per-task together": {
        # threads are not in the dry run's resources; the submission test checks them
        "*": {"cpus_per_task": ABSENT, "slurm_partition": ABSENT},
    },
    "CPUs of one rule: only sbatch --cpus-per-task (the rule keeps its threads)": {
        "features": {"cpus_per_task": "2"},
        "*": {"cpus_per_task": ABSENT},
    },
}


def documented_commands() -> dict[str, str]:
    """The command lines of the docs' section, by the comment line above each."""
    text = DOCS.read_text()
    assert SECTION in text, f"{DOCS} lost its section {SECTION!r}"
    block = re.search(r"```bash\n(.*?)```", text.split(SECTION, 1)[1], flags=re.DOTALL)
    assert block is not None, f"no ```bash block in {SECTION!r}"
    commands, label = {}, None
    for line in block.group(1).replace("\\\n", " ").splitlines():
        line = line.strip()
        if line.startswith("# "):
            label = line[2:]
        elif line:
            assert label is not None and label not in commands, line
            commands[label] = line
    return commands


def dry_run_jobs(output: str) -> list[tuple[str, dict[str, str]]]:
    """(rule, resources) of every job a dry run lists."""
    jobs = []
    for line in output.splitlines():
        header = re.match(r"(?:local)?rule (\w+):$", line)
        if header:
            jobs.append((header.group(1), {}))
        elif jobs and line.startswith("    resources: "):
            items = line.removeprefix("    resources: ").split(", ")
            jobs[-1][1].update(item.split("=", 1) for item in items)
    return jobs


def write_workflow(workdir: Path, **backbone) -> Path:
    """A small dataset named like the docs' one; features and segments run models (DINOv2,
    SAM: no weights are needed to plan), so with `device: auto` they ask for a GPU."""
    make_dataset(workdir / "data" / "toy")
    config = toy_config(workdir / "data")
    config["datasets"] = {DATASET: config["datasets"]["toy"]}
    config["targets"] = [DATASET]
    config["datasets"][DATASET]["defaults"] = {
        "features": "dinov2_vitg14",
        "segmenter": "sam_vith",
    }
    config["backbones"]["dinov2_vitg14"].update(backbone)
    assert config["device"] == "auto"
    return write_config(workdir, config)


@pytest.fixture(scope="module")
def dry_workdir(tmp_path_factory) -> tuple[Path, Path]:
    workdir = tmp_path_factory.mktemp("cli")
    return workdir, write_workflow(workdir)


def as_test_run(command: str, workdir: Path, config: Path) -> list[str]:
    """A documented command line, run as a dry run in ``workdir`` with ``config``: only
    the program and the profile's (relative) path change, options go in front."""
    argv = shlex.split(command)
    assert argv[0] == "snakemake", command
    argv = [str(SLURM_PROFILE) if a == "workflow/profiles/slurm" else a for a in argv[1:]]
    return [
        sys.executable, "-m", "snakemake",
        "--snakefile", str(SNAKEFILE),
        "--directory", str(workdir),
        "--configfile", str(config),
        "-n",
        *argv,
    ]  # fmt: skip


def test_docs_list_the_tested_command_lines():
    assert set(documented_commands()) == set(EXPECTED)


@pytest.mark.parametrize("label", list(EXPECTED))
def test_documented_command_line(label, dry_workdir):
    workdir, config = dry_workdir
    command = documented_commands()[label]
    proc = dry_run(as_test_run(command, workdir, config), workdir, slurm_environment())
    output = proc.stdout + proc.stderr
    assert proc.returncode == 0, output[-3000:]
    jobs = dry_run_jobs(output)
    rules = {rule for rule, _ in jobs}
    assert {"images", "dataset", "features", "segments", "recall"} <= rules, output[-3000:]
    expected = EXPECTED[label]
    for rule, resources in jobs:
        if rule in LOCAL_RULES:
            continue
        where = f"{label}: job of rule {rule}: {resources}"
        for name, value in {**expected["*"], **expected.get(rule, {})}.items():
            assert resources.get(name) == value, f"{name}: {where}"
        if rule in OWN_RESOURCES:  # the rule's own memory and time survive the override
            mem_mb, runtime = OWN_RESOURCES[rule]
            assert resources.get("mem_mb") == str(mem_mb), where
            assert resources.get("runtime") == str(runtime), where
        if rule in {"features", "segments"}:  # the rules' GPU request survives too
            assert resources.get("gpu") == "1", where


@pytest.mark.parametrize(
    "option, error",
    [
        ("--default-resources", "dictionary update sequence element #1 has length 1"),
        ("--set-resources", "not enough values to unpack (expected 2, got 1)"),
    ],
)
def test_target_after_a_resource_option_is_read_as_a_resource(option, error, dry_workdir):
    """What docs/cluster.md warns about: Snakemake's own parsing, not fixable here."""
    workdir, config = dry_workdir
    value = {"--default-resources": "slurm_partition=cpu"}.get(option, "features:gpu=0")
    command = f"snakemake --profile workflow/profiles/slurm {option} {value} {TARGET}"
    proc = dry_run(as_test_run(command, workdir, config), workdir, slurm_environment())
    assert proc.returncode != 0
    assert error in proc.stdout + proc.stderr, proc.stderr[-3000:]


def _option(argv: list[str], flag: str) -> str:
    assert flag in argv, (flag, argv)
    return argv[argv.index(flag) + 1]


def test_command_line_overrides_reach_sbatch_and_slurm(slurm_cluster, tmp_path):
    from tiny_models import save_tiny_dinov2

    workdir = tmp_path / "run"
    workdir.mkdir()
    # a real (tiny, random) DINOv2, so `features` asks for its GPU through the rule
    model = save_tiny_dinov2(tmp_path / "dinov2")
    config = write_workflow(workdir, model=str(model), layer=1)
    bin_dir, calls = gpu_stripping_wrappers(tmp_path / "wrappers")
    share = node_memory_share_mb(slurm_cluster)
    everywhere = slurm_cluster.partition  # the test cluster's default partition, "debug"
    with extra_partition(slurm_cluster, "gpu"):
        command = [
            sys.executable, "-m", "snakemake",
            "--snakefile", str(SNAKEFILE),
            "--directory", str(workdir),
            "--configfile", str(config),
            "--profile", str(SLURM_PROFILE),
            TARGET, "--until", "features",  # images + features: two jobs
            *cluster_limits(slurm_cluster),
            "--slurm-keep-successful-logs",
            "--slurm-init-seconds-before-status-checks", "2",
            "--seconds-between-status-checks", "2",
            # the overrides, as docs/cluster.md writes them
            "--default-resources", f"slurm_partition={everywhere}", "slurm_account=vprflow",
            "--set-resources", "features:slurm_partition=gpu", "features:gpu_model=a100",
            "--set-threads", "features=1",
        ]  # fmt: skip
        output, seconds = run_snakemake(command, cwd=workdir, path_prefix=bin_dir)
        job_ids = submitted_job_ids(output)
        info = slurm_job_info(job_ids)
    print(f"2 jobs through sbatch in {seconds:.0f} s")
    assert len(job_ids) == 2, output[-4000:]

    # what sbatch received, by rule (`--comment rule_<rule>_wildcards_...`)
    sbatch = {}
    for argv in wrapped_calls(calls, "sbatch"):
        rule = re.match(r"rule_([a-z]+)_", _option(argv, "--comment")).group(1)
        sbatch[rule] = argv
    assert sorted(sbatch) == ["features", "images"], sbatch
    features, images = sbatch["features"], sbatch["images"]
    assert _option(features, "-p") == "gpu" and _option(images, "-p") == everywhere
    assert _option(features, "-A") == "vprflow" == _option(images, "-A")
    assert "--gpus=a100:1" in features  # the rule's gpu=1 with the command line's model
    assert not any(a.startswith("--gpus") for a in images), images
    assert "--cpus-per-task=1" in features and "--cpus-per-task=1" in images
    # the rules' own memory and time, under the node's cap (cluster_limits)
    assert _option(features, "-t") == "120" and _option(images, "-t") == "60"
    assert _option(features, "--mem") == str(min(16000, share))
    assert _option(images, "--mem") == str(min(4000, share))
    # inside the features job, the job step asked for the rule's GPU and 1 CPU
    steps = [argv for argv in wrapped_calls(calls, "srun") if "--gpus=1" in argv]
    assert len(steps) == 1 and "--cpus-per-task=1" in steps[0], wrapped_calls(calls, "srun")

    # what SLURM ran
    logs = (workdir / ".snakemake" / "slurm_logs").rglob("*.log")
    rule_of = {int(p.stem): p.relative_to(workdir).parts[2].removeprefix("rule_") for p in logs}
    assert sorted(rule_of) == sorted(job_ids), rule_of
    for job_id, fields in info.items():
        rule = rule_of[job_id]
        assert fields.get("JobState") == "COMPLETED", (rule, fields)
        assert fields.get("Account") == "vprflow", (rule, fields)
        assert fields.get("NumCPUs") == "1", (rule, fields)
        mem_mb, runtime = OWN_RESOURCES[rule]
        assert fields.get("MinMemoryNode") == f"{min(mem_mb, share)}M", (rule, fields)
        assert fields.get("TimeLimit") == f"{runtime // 60:02d}:{runtime % 60:02d}:00"
        partition = "gpu" if rule == "features" else everywhere
        assert fields.get("Partition") == partition, (rule, fields)
