"""Running the real Snakefile in a temporary working directory."""

from __future__ import annotations

import atexit
import copy
import csv
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
SNAKEFILE = REPO / "workflow" / "Snakefile"
SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"


def in_ci() -> bool:
    """Whether this is CI (``CI=true``), where a test that cannot run fails rather than
    skips. Here, not in conftest.py: ``from conftest import`` takes whichever folder's
    conftest.py was imported last (tests/stages/ has its own)."""
    return os.environ.get("CI", "").lower() in {"1", "true", "yes"}


def with_schema_defaults(definition: str, **instance) -> dict:
    """``instance`` with every default the schema's ``definition`` declares filled in, as
    the workflow fills a config before a stage sees it: ``"dataset"``, or
    ``"dataset/properties/ground_truth"`` for a ground-truth spec."""
    from vprflow.planning.config import fill_defaults

    schema = yaml.safe_load(SCHEMA.read_text())
    return fill_defaults(instance, schema, f"#/definitions/{definition}")


def dataset_spec(**spec) -> dict:
    return with_schema_defaults("dataset", **spec)


def truth_spec(**spec) -> dict:
    return with_schema_defaults("dataset/properties/ground_truth", **spec)


def repo_config() -> dict:
    return yaml.safe_load((REPO / "config" / "config.yaml").read_text())


def committed_config() -> dict | None:
    """config/config.yaml as committed (None outside a git checkout)."""
    committed = subprocess.run(
        ["git", "-C", str(REPO), "show", "HEAD:config/config.yaml"],
        capture_output=True,
        text=True,
    )
    return yaml.safe_load(committed.stdout) if committed.returncode == 0 else None


def toy_config(data_root: Path, **dataset_overrides) -> dict:
    """The shipped config with one small dataset ``toy`` and small model sizes."""
    config = copy.deepcopy(repo_config())
    config["data_root"] = str(data_root)
    config["datasets"] = {
        "toy": {
            "path": "toy",
            "reference": "ref",
            "query": "query",
            "resolution": [96, 72],
            "ground_truth": {"kind": "vprbench", "file": "ground_truth_new.npy"},
            "recall_at": [1, 5, 10, 20],
            "methods": [
                "anyloc_vlad",
                "segvlad_o0_nopca",
                "segvlad_o0",
                "segvlad_nopca",
                "segvlad",
            ],
            **dataset_overrides,
        }
    }
    config["targets"] = ["toy"]
    config["segmenters"]["slic"]["n_segments"] = 12
    config["vocabulary"]["n_clusters"] = 4
    config["vocabulary"]["n_iter"] = 10
    config["pca"]["dim"] = 16
    return config


def write_config(workdir: Path, config: dict, name: str = "config.yaml") -> Path:
    path = workdir / name
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path


def snakemake_command(workdir: Path, config_path: Path, *args: str, cores: int = 2) -> list[str]:
    return [
        sys.executable,
        "-m",
        "snakemake",
        "--snakefile",
        str(SNAKEFILE),
        "--directory",
        str(workdir),
        "--configfile",
        str(config_path),
        "--cores",
        str(cores),
        *args,
    ]


# Answers dry runs for one pytest process: Snakemake's command line (`snakemake.cli.main`)
# run in a long-lived process, as `python -m snakemake` runs it, so that each dry run
# does not import Snakemake and its plugins again (1.1 s of the 1.7 s one takes as a
# command). One request, one dry run: a JSON line of argv, working directory and
# environment in; a JSON line of exit status, stdout and stderr out.
DRY_RUN_SERVER = r"""
import json, os, sys, tempfile
from snakemake.cli import main
answers = os.fdopen(os.dup(1), "w")
for line in sys.stdin:
    request = json.loads(line)
    os.environ.clear(); os.environ.update(request["env"])
    os.chdir(request["cwd"])
    sys.argv = ["snakemake", *request["argv"]]
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        saved = [os.dup(1), os.dup(2)]
        sys.stdout.flush(); sys.stderr.flush()
        os.dup2(out.fileno(), 1); os.dup2(err.fileno(), 2)
        try:
            main(request["argv"])
            code = 0
        except SystemExit as exit:
            code = exit.code if isinstance(exit.code, int) else 1
        except BaseException as error:
            print(repr(error), file=sys.stderr)
            code = 1
        finally:
            sys.stdout.flush(); sys.stderr.flush()
            os.dup2(saved[0], 1); os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
        out.seek(0); err.seek(0)
        streams = [f.read().decode(errors="replace") for f in (out, err)]
    answers.write(json.dumps({"code": code, "stdout": streams[0], "stderr": streams[1]}) + "\n")
    answers.flush()
"""
_server: list[subprocess.Popen] = []


def dry_run(
    command: list[str], cwd: Path, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess:
    """``command`` (``python -m snakemake ... -n``) answered by this process's dry-run
    server, in ``env`` (this process's environment at the time of the call)."""
    if not _server or _server[0].poll() is not None:
        _server[:] = [
            subprocess.Popen(
                [sys.executable, "-c", DRY_RUN_SERVER],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                text=True,
            )
        ]
        atexit.register(_server[0].stdin.close)
    server = _server[0]
    argv = command[3:]  # after `python -m snakemake`
    request = {"argv": argv, "cwd": str(cwd), "env": dict(os.environ if env is None else env)}
    server.stdin.write(json.dumps(request) + "\n")
    server.stdin.flush()
    answer = json.loads(server.stdout.readline())
    return subprocess.CompletedProcess(command, answer["code"], answer["stdout"], answer["stderr"])


def snakemake(
    workdir: Path, config_path: Path, *args: str, check: bool = True
) -> subprocess.CompletedProcess:
    command = snakemake_command(workdir, config_path, *args)
    if "-n" in args or "--dry-run" in args:
        result = dry_run(command, workdir)
    else:
        result = subprocess.run(command, capture_output=True, text=True, cwd=workdir)
    if check and result.returncode != 0:
        raise AssertionError(
            f"snakemake {' '.join(args)} failed ({result.returncode}):\n"
            f"{result.stdout[-3000:]}\n{result.stderr[-5000:]}"
        )
    return result


def scheduled_outputs(workdir: Path, config_path: Path, *targets: str) -> list[str]:
    """The ``output:`` lines of a dry run for ``targets``: each job's outputs, joined by
    ", "."""
    result = snakemake(workdir, config_path, "-n", *targets)
    text = result.stdout + result.stderr
    if "Nothing to be done" in text:
        return []
    return re.findall(r"^\s+output: (.+)$", text, flags=re.MULTILINE)


def scheduled_files(workdir: Path, config_path: Path, *targets: str) -> set[str]:
    """Every output a dry run for ``targets`` would (re)build."""
    lines = scheduled_outputs(workdir, config_path, *targets)
    return {output.strip() for line in lines for output in line.split(", ")}


def scheduled_stages(workdir: Path, config_path: Path, target: str) -> set[str]:
    """Stage names (``results/cache/<stage>/...``), and ``recall_csv`` for the table, that
    a dry run schedules."""
    stages = set()
    for output in scheduled_files(workdir, config_path, target):
        match = re.match(r"results/cache/([a-z]+)/", output)
        stages.add(match.group(1) if match else "recall_csv")
    return stages


def read_rows(path: Path) -> list[dict]:
    """A CSV table's rows."""
    with open(path) as f:
        return list(csv.DictReader(f))


def expected_rows(dataset: dict) -> list[str]:
    """The rows a dataset entry's table has, in order: each method, then its re-ranked
    rows ``<method>+<reranker>``."""
    rerank = dataset.get("rerank") or {}
    rows = []
    for method in dataset["methods"]:
        rows += [method, *(f"{method}+{r}" for r in rerank.get(method, []))]
    return rows


# Columns that time the run that built a row: the only ones that differ between runs.
TIMED_COLUMNS = ("search_ms_per_query", "rerank_ms_per_query")


def untimed_table(path: Path) -> tuple[list[str], list[dict]]:
    """A results CSV's header and rows with the :data:`TIMED_COLUMNS` blanked, after
    checking every search was timed."""
    import csv

    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        rows = list(reader)
    assert rows and all(float(row["search_ms_per_query"]) > 0 for row in rows), path
    for row in rows:
        for column in TIMED_COLUMNS:
            row[column] = ""
    return list(reader.fieldnames), rows


def run_stage(
    plan, stage: str, key: str, data_root: Path, out: Path, done: dict, run: dict | None = None
) -> str:
    """Run ``(stage, key)`` of ``plan`` and its inputs, unsharded, through the rules' own
    runners in this process (``run``: the run params, default the CPU); the store's
    path. ``done`` maps the ``(stage, key)`` already run to their stores."""
    from vprflow.stages.jobs import Job, run_job

    if (stage, key) not in done:
        planned = plan.get(stage, key)
        inputs = {
            n: run_stage(plan, *ref, data_root, out, done, run) for n, ref in planned.inputs.items()
        }
        path = str(out / stage / f"{key}.zarr")
        job = Job(
            planned.record, inputs, path, data_root=str(data_root), run=run or {"device": "cpu"}
        )
        run_job(job)
        done[stage, key] = path
    return done[stage, key]


def table_in_process(config: dict, workdir: Path, dataset: str) -> Path:
    """``dataset``'s recall table (``results/recall_<dataset>.csv`` under ``workdir``)
    of ``config``, planned as the Snakefile plans it and computed through the rules' own
    runners in this process (stores under ``workdir/results/cache``): for tests of what a
    table holds, where a Snakemake run's job starts would cost more than the work."""
    from vprflow.planning.config import validate_config
    from vprflow.planning.plan import build_plan

    plan = build_plan(validate_config(copy.deepcopy(config), SCHEMA))
    return write_table(plan, dataset, Path(config["data_root"]), workdir, {})


def built_stores(plan, workdir: Path) -> dict[tuple[str, str], str]:
    """``(stage, key) -> path`` of every store of ``plan`` that a run in ``workdir`` has
    finished: :func:`run_stage`'s ``done``, to compute only what that run lacks."""
    from vprflow.core.paths import store_path

    built = {}
    for stage, keys in plan.stages.items():
        for key in keys:
            path = workdir / store_path(stage, key)
            if path.is_dir():
                built[stage, key] = str(path)
    return built


def write_table(plan, dataset: str, data_root: Path, workdir: Path, done: dict) -> Path:
    """:func:`table_in_process` of a ``plan`` already made; ``done`` as :func:`run_stage`'s,
    with every store run for the table added."""
    from vprflow.core.paths import CACHE, RECALL_CSV
    from vprflow.stages.report import write_recall_csv

    runs, cache = plan.runs[dataset], workdir / CACHE
    recalls = [run_stage(plan, "recall", run.recall_key, data_root, cache, done) for run in runs]
    table = workdir / RECALL_CSV.format(dataset=dataset)
    table.parent.mkdir(parents=True, exist_ok=True)
    rows = [{"method": run.method, "params": run.row_params} for run in runs]
    write_recall_csv(dataset, rows, recalls, str(table))
    return table
