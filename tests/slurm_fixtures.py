"""Shared pieces for tests that run Snakemake on a real (local, single-node) SLURM cluster.

Use from tests/conftest.py (or a test module)::

    from slurm_fixtures import slurm_cluster  # noqa: F401  (pytest fixture)

and in a test::

    @pytest.mark.slurm
    def test_x(slurm_cluster, tmp_path):
        cmd = snakemake_slurm_command(slurm_cluster, tmp_path / "Snakefile", tmp_path)
        run_snakemake(cmd, cwd=tmp_path)

The cluster is started by scripts/local_slurm.py (needs root and the Debian packages
that scripts/install_slurm.sh installs). Without them the fixture skips the test, or
fails it when CI=true (CI must not silently lose the SLURM coverage).
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from workflow_helpers import in_ci

REPO = Path(__file__).resolve().parents[1]
SLURM_PROFILE = REPO / "workflow" / "profiles" / "slurm"

sys.path.insert(0, str(REPO / "scripts"))
import local_slurm  # noqa: E402

# Snakemake prints one line per submission, e.g.
# "Job 3 has been submitted with SLURM jobid 17 (log: /.../17.log)."
SUBMITTED_RE = re.compile(r"submitted with SLURM jobid (\d+)")


def slurm_unavailable_reason() -> str | None:
    """Why a local SLURM cluster cannot be started here, or None if it can."""
    if importlib.util.find_spec("snakemake_executor_plugin_slurm") is None:
        return 'the SLURM executor is an extra: pip install -e ".[slurm]"'
    if os.geteuid() != 0:
        return "the local SLURM cluster needs root"
    if shutil.which("sbatch") is None:
        return "sbatch is not installed (run: bash scripts/install_slurm.sh)"
    missing = local_slurm.missing_tools()
    if missing:
        return f"not installed: {', '.join(missing)} (run: bash scripts/install_slurm.sh)"
    return None


@pytest.fixture(scope="session")
def slurm_cluster(tmp_path_factory):
    """A running single-node SLURM cluster (local_slurm.ClusterHandle); stopped afterwards."""
    reason = slurm_unavailable_reason()
    if reason is not None:
        if in_ci():
            pytest.fail(f"CI=true but SLURM tests cannot run: {reason}", pytrace=False)
        pytest.skip(reason)
    handle = local_slurm.start_cluster(tmp_path_factory.mktemp("slurm"))
    try:
        yield handle
    finally:
        local_slurm.stop_cluster(handle)


# --------------------------------------------------------------------------- profile


def _format_value(value) -> str:
    return str(value).lower() if isinstance(value, bool) else str(value)


def node_memory_share_mb(cluster: local_slurm.ClusterHandle) -> int:
    """Memory one job may ask for: RealMemory / CPUs, so that jobs can run side by side."""
    return cluster.real_memory_mb // max(1, cluster.cpus)


def cluster_limits(cluster: local_slurm.ClusterHandle) -> list[str]:
    """Options that keep every job within the test node, whatever asks for more.

    ``--max-threads`` caps threads (and so ``--cpus-per-task``) at the node's CPUs;
    ``--resources mem_mb=N`` caps each job's ``mem_mb`` at N in cluster mode (``mem_mb``
    is a per-job resource there, so it does not limit how many jobs run at once),
    including the values the rules set in their own ``resources:``. Neither is one of
    the keys a user overrides (``--default-resources`` / ``--set-resources``).
    """
    return [
        "--max-threads", str(cluster.cpus),
        "--resources", f"mem_mb={node_memory_share_mb(cluster)}",
    ]  # fmt: skip


def _cap(name: str, value, cluster: local_slurm.ClusterHandle):
    """A resource value that fits the test cluster: no GPUs, <= its CPUs and memory."""
    mem_cap = node_memory_share_mb(cluster)
    caps = {"cpus_per_task": cluster.cpus, "mem_mb": mem_cap, "mem_mb_per_cpu": mem_cap}
    if name in {"gpu", "gpus"}:
        return 0
    if name in {"gpu_model", "gres", "slurm_partition", "slurm_account", "qos", "constraint"}:
        return None  # this cluster has none of these: drop the request
    if name in caps:
        if isinstance(value, int | float):
            return min(int(value), caps[name])
        # an expression such as "16000 * attempt" or "threads": evaluated by Snakemake
        return f"min({value}, {caps[name]})"
    return value


def fit_profile_to_cluster(
    cluster: local_slurm.ClusterHandle, profile: Path = SLURM_PROFILE
) -> list[str]:
    """Command-line overrides that make ``profile`` run on the test cluster.

    Takes the profile's own ``default-resources`` and ``set-resources`` and changes only
    what this cluster cannot provide: GPU requests become 0, partition/account/QoS/
    constraint requests are dropped, CPUs and memory are capped at what the node has
    (memory at RealMemory / CPUs so that jobs can run side by side). Also adds
    :func:`cluster_limits` (threads beyond the node's CPUs could never be scheduled; the
    rules' own memory requests are capped too).
    A command-line option replaces the profile's whole key, so both keys are rebuilt in full.
    """
    config = yaml.safe_load((profile / "config.yaml").read_text()) or {}
    args: list[str] = cluster_limits(cluster)
    defaults = config.get("default-resources") or {}
    default_items = []
    for name, value in defaults.items():
        fitted = _cap(name, value, cluster)
        if fitted is not None:
            default_items.append(f"{name}={_format_value(fitted)}")
    if default_items:
        args += ["--default-resources", *default_items]
    set_items = []
    for rule, resources in (config.get("set-resources") or {}).items():
        for name, value in (resources or {}).items():
            fitted = _cap(name, value, cluster)
            if fitted is not None:
                set_items.append(f"{rule}:{name}={_format_value(fitted)}")
    # The workflow's model stages request a GPU themselves; this cluster has none.
    set_items += [f"{rule}:gpu=0" for rule in ("features", "segments")]
    args += ["--set-resources", *set_items]
    return args


def snakemake_slurm_command(
    cluster: local_slurm.ClusterHandle,
    snakefile: Path,
    workdir: Path,
    *extra: str,
    profile: Path = SLURM_PROFILE,
    fast_status_checks: bool = True,
) -> list[str]:
    """``snakemake --executor slurm --profile <repo profile>`` plus the test cluster's overrides.

    ``fast_status_checks`` polls squeue every few seconds instead of the plugin's
    default (first check after 40 s), which would dominate a small test's runtime.
    """
    cmd = [
        sys.executable, "-m", "snakemake",
        "--snakefile", str(snakefile),
        "--directory", str(workdir),
        "--executor", "slurm",
        "--profile", str(profile),
        *fit_profile_to_cluster(cluster, profile),
        "--slurm-keep-successful-logs",
    ]  # fmt: skip
    if fast_status_checks:
        cmd += [
            "--slurm-init-seconds-before-status-checks", "1",
            "--seconds-between-status-checks", "1",
        ]  # fmt: skip
    return cmd + list(extra)


def slurm_environment() -> dict[str, str]:
    """This process's environment for a Snakemake command on the test cluster: no
    ``SLURM_*`` variable of an enclosing job, no profile of the user's."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("SLURM_")}
    env.pop("SNAKEMAKE_PROFILE", None)
    return env


def run_snakemake(
    cmd: list[str], cwd: Path, timeout: float = 600, path_prefix: Path | None = None
) -> tuple[str, float]:
    """Run a Snakemake command; return (combined output, wall seconds). Fails with the output.

    ``path_prefix``: a directory put first on PATH (e.g. :func:`gpu_stripping_wrappers`).
    """
    env = slurm_environment()
    if path_prefix is not None:
        env["PATH"] = f"{path_prefix}{os.pathsep}{env.get('PATH', '')}"
    start = time.monotonic()
    proc = subprocess.run(
        cmd,
        cwd=cwd,
        env=env,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        timeout=timeout,
        check=False,
    )
    seconds = time.monotonic() - start
    if proc.returncode != 0:
        pytest.fail(
            f"snakemake exited with {proc.returncode} after {seconds:.0f} s\n"
            f"$ {' '.join(cmd)}\n{proc.stdout[-8000:]}",
            pytrace=False,
        )
    return proc.stdout, seconds


def submitted_job_ids(output: str) -> list[int]:
    """SLURM job ids that Snakemake reported as submitted."""
    return [int(m) for m in SUBMITTED_RE.findall(output)]


def slurm_job_info(job_ids: list[int]) -> dict[int, dict[str, str]]:
    """``scontrol show job`` fields of finished jobs (kept for MinJobAge = 10 min)."""
    info = {}
    for job_id in job_ids:
        out = subprocess.run(
            ["scontrol", "show", "job", "--oneliner", str(job_id)],
            capture_output=True, text=True, check=False,
        )  # fmt: skip
        fields = {}
        for token in out.stdout.split():
            key, sep, value = token.partition("=")
            if sep:
                fields[key] = value
        info[job_id] = fields
    return info


# --------------------------------------------------------------------------- overrides

_WRAPPER = """#!{python}
# Written by tests/slurm_fixtures.py: log the call, then run the real {name} without GPU
# requests (the test node has no GPUs).
import json, os, sys
with open({log!r}, "a") as log:
    log.write(json.dumps([{name!r}, *sys.argv[1:]]) + "\\n")
args = [a for a in sys.argv[1:] if not a.startswith("--gpus=")]
os.execv({real!r}, [{real!r}, *args])
"""


def gpu_stripping_wrappers(directory: Path) -> tuple[Path, Path]:
    """``sbatch`` and ``srun`` wrappers for the GPU-less test node; returns (bin dir, log).

    Each wrapper appends its arguments (a JSON list, the command's name first) to the
    log and runs the real command with every ``--gpus=...`` argument removed, so that a
    job that asks for a GPU (``sbatch --gpus=a100:1``, and the job step's own
    ``srun --gpus=1``) still runs here, while the log shows what was asked for. Put the
    bin dir first on PATH (``run_snakemake(..., path_prefix=bin_dir)``); ``sbatch
    --export=ALL`` hands that PATH on to the job, whose ``srun`` is then wrapped too.
    """
    bin_dir = directory / "bin"
    bin_dir.mkdir(parents=True, exist_ok=True)
    log = directory / "calls.jsonl"
    for name in ("sbatch", "srun"):
        real = shutil.which(name)
        if real is None:
            pytest.fail(f"{name} is not on PATH", pytrace=False)
        wrapper = bin_dir / name
        wrapper.write_text(
            _WRAPPER.format(python=sys.executable, name=name, log=str(log), real=real)
        )
        wrapper.chmod(0o755)
    return bin_dir, log


def wrapped_calls(log: Path, name: str) -> list[list[str]]:
    """Argument lists the wrapper ``name`` (sbatch or srun) received, in call order."""
    if not log.exists():
        return []
    calls = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
    return [call[1:] for call in calls if call[0] == name]


@contextlib.contextmanager
def extra_partition(cluster: local_slurm.ClusterHandle, name: str):
    """A second partition ``name`` on the test node while the block runs (``scontrol
    create``), deleted afterwards; read the jobs' ``scontrol`` fields inside the block."""
    created = subprocess.run(
        ["scontrol", "create", f"PartitionName={name}", f"Nodes={cluster.node}",
         "MaxTime=INFINITE", "State=UP"],
        capture_output=True, text=True, check=False,
    )  # fmt: skip
    if created.returncode != 0:
        pytest.fail(f"scontrol create partition {name}: {created.stderr}", pytrace=False)
    try:
        yield name
    finally:
        subprocess.run(
            ["scontrol", "delete", f"PartitionName={name}"],
            capture_output=True, text=True, check=False,
        )  # fmt: skip
