"""Shared fixtures: the real datasets under $VPRFLOW_DATA, the SLURM cluster, and a tiny
model of each SAM kind."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest
from filelock import FileLock
from slurm_fixtures import slurm_cluster  # noqa: F401  (re-exported fixture)
from workflow_helpers import in_ci

# Idle OpenMP threads (torch's) sleep instead of spinning, as in the workflow's jobs
# (vprflow.stages.runner): beside the other xdist workers, spinning threads took a fifth
# of the CPU the model tests used (60 against 49 CPU s for test_sam_generator, test_vit
# and test_trunks on three workers, the same wall time). Set before a test imports torch;
# a user's own value wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# numpy's OpenBLAS threads likewise (vprflow.stages.runner): the tests' own children
# (code paths, benchmarks) import numpy before vprflow's runner, or never import it.
os.environ.setdefault("OPENBLAS_THREAD_TIMEOUT", "4")

# The SLURM executor plugin, where installed (the `slurm` extra), runs `scontrol show
# config` when Snakemake imports it, at every start: 9 s where a slurm.conf names a
# controller that does not answer (or its DNS look-up hangs). Local runs need no cluster,
# so every test not marked `slurm` points SLURM at an empty configuration, which scontrol
# refuses at once; the SLURM tests keep the machine's own.
NO_CLUSTER = {"SLURM_CONF": os.devnull}


@pytest.fixture(autouse=True)
def no_cluster_probe(request, monkeypatch):
    if request.node.get_closest_marker("slurm") is None:
        for name, value in NO_CLUSTER.items():
            monkeypatch.setenv(name, value)


@pytest.fixture(scope="session")
def data_root() -> Path:
    """``$VPRFLOW_DATA``: missing data skips locally and fails under CI=true."""
    value = os.environ.get("VPRFLOW_DATA")
    if not value or not Path(value).is_dir():
        message = f"VPRFLOW_DATA is {value!r}, not a folder with the shared datasets"
        if in_ci():
            pytest.fail(message, pytrace=False)
        pytest.skip(message)
    return Path(value).resolve()


def built_once(tmp_path_factory, name: str, build: Callable[[Path], None]) -> Path:
    """A folder ``name`` filled by ``build(folder)`` once per pytest run, however many
    pytest-xdist workers ask: the first builds it under a file lock while the others
    wait. A build that raised leaves no mark of being done, so the next worker to ask
    builds again (and reports its own failure)."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the run's folder, above each worker's own
    folder, done = root / name, root / f"{name}.done"
    with FileLock(root / f"{name}.lock"):
        if not done.exists():
            shutil.rmtree(folder, ignore_errors=True)
            folder.mkdir()
            # A session fixture is set up before the function-scoped no_cluster_probe.
            with pytest.MonkeyPatch.context() as patch:
                for variable, value in NO_CLUSTER.items():
                    patch.setenv(variable, value)
                build(folder)
            done.touch()
    return folder


@pytest.fixture(scope="session")
def corridor_run(tmp_path_factory, data_root):
    """The shipped config's default run (`snakemake` with no target: corridor's tables and
    figures), then `snakemake --report report.html`; built once for all pytest-xdist
    workers and shared by the tests that read them. Returns ``(workdir, report path)``."""
    from workflow_helpers import repo_config, snakemake, write_config

    def build(workdir: Path) -> None:
        config = repo_config()
        config["data_root"] = str(data_root)
        config["targets"] = ["corridor"]
        config_path = write_config(workdir, config)
        snakemake(workdir, config_path)
        snakemake(workdir, config_path, "--report", "report.html")

    workdir = built_once(tmp_path_factory, "corridor", build)
    return workdir, workdir / "report.html"


@pytest.fixture(scope="session")
def roadscene_run(tmp_path_factory, data_root) -> Path:
    """The shipped roadscene table (RGB references, thermal queries) planned as the
    Snakefile plans it and computed in this process (workflow_helpers.table_in_process:
    a third of a Snakemake run's CPU, its jobs' starts the rest); the working directory,
    stores under ``results/cache``. The corridor run is the suite's Snakemake run of the
    shipped data."""
    from workflow_helpers import repo_config, table_in_process

    def build(workdir: Path) -> None:
        config = repo_config()
        config["data_root"] = str(data_root)
        config["targets"] = ["roadscene"]
        table_in_process(config, workdir, "roadscene")

    return built_once(tmp_path_factory, "roadscene", build)


@pytest.fixture(scope="session")
def benchmarks_smoke_run(tmp_path_factory, data_root) -> Path:
    """The Snakemake run that the benchmarks' smoke modes which read one share
    (benchmarks/smoke_run.py), made by ``bench_city.py --make-smoke-run`` once for all
    pytest-xdist workers: three runs of ~12 CPU seconds fewer."""
    script = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_city.py"

    def build(folder: Path) -> None:
        command = [sys.executable, str(script), "--make-smoke-run", str(folder)]
        made = subprocess.run(command + ["--data", str(data_root)], capture_output=True, text=True)
        if made.returncode:
            raise RuntimeError(f"{' '.join(command)} failed:\n{made.stderr[-4000:]}")

    return built_once(tmp_path_factory, "smoke-run", build)


@pytest.fixture(scope="module", params=("sam", "sam_hq", "sam2"))
def sam_kind_model(request, tmp_path_factory):
    """``(kind, path, model)``: a tiny random model of each SAM kind saved to ``path``
    (``test_sam_adapters``, ``test_sam_generator``). Well-conditioned weights (as
    ``test_sam_generator``'s reference model): float32 logits of separately batched calls
    agree to ~1e-5."""
    from tiny_models import tiny_sam, tiny_sam2, tiny_sam_hq

    kind = request.param
    build = {"sam": tiny_sam, "sam_hq": tiny_sam_hq, "sam2": tiny_sam2}[kind]
    model = build(model_size=128, seed=3, scale=0.3)
    path = tmp_path_factory.mktemp(kind)
    model.save_pretrained(path)
    return kind, path, model


# How pytest-xdist shares the suite between its workers (pyproject.toml's addopts): whole
# modules to a worker, as `--dist loadscope` does, so that a module's fixtures (such as
# test_workflow.py's toy run) are built once; the SLURM modules together, because they
# share one local SLURM cluster, which a second worker could not start beside it. The
# end-to-end modules (Snakemake runs, the shared data, SLURM, the benchmarks' smoke runs)
# take most of the suite's time: they are collected first and so handed out first, and the
# many quick modules fill the workers' time around them.
SLOW_MARKERS = ("workflow", "data", "slurm", "benchmark")


# Modules whose tests share nothing but are each a long process of their own: one test
# is one unit of work, so that both workers take them.
ONE_TEST_A_UNIT = ("test_benchmarks.py",)


def work_unit(nodeid: str) -> str:
    """The unit of work pytest-xdist hands to one worker: a test's module, the test itself
    in :data:`ONE_TEST_A_UNIT`, or ``slurm``."""
    module = nodeid.split("::", 1)[0]
    if Path(module).name in ONE_TEST_A_UNIT:
        return nodeid
    return "slurm" if Path(module).name.startswith("test_slurm") else module


# The longest units, first of all: the SLURM tests wait on the scheduler for minutes, the
# code paths' runs and the corridor run take a worker's CPU for minutes.
LONGEST = ("slurm", "tests/workflow/test_code_paths.py", "tests/workflow/test_real_data.py")


def pytest_collection_modifyitems(items):
    slow = {
        work_unit(item.nodeid) for item in items if any(map(item.get_closest_marker, SLOW_MARKERS))
    }

    def order(item) -> tuple[bool, int]:
        unit = work_unit(item.nodeid)
        return unit not in slow, LONGEST.index(unit) if unit in LONGEST else len(LONGEST)

    items.sort(key=order)


class WorkUnits:
    """pytest-xdist's hook, registered where the plugin is (`-p no:xdist` leaves it out)."""

    @staticmethod
    def pytest_xdist_make_scheduler(config, log):
        from xdist.scheduler import LoadScopeScheduling

        class WorkUnitScheduling(LoadScopeScheduling):
            def _split_scope(self, nodeid: str) -> str:
                return work_unit(nodeid)

        return WorkUnitScheduling(config, log)


def pytest_configure(config):
    if config.pluginmanager.hasplugin("xdist"):
        config.pluginmanager.register(WorkUnits())
