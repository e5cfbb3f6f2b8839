"""Each stage's fixed cost: one job of it where the per-image work is negligible, beside
``python -c pass`` and the pieces of a job's start-up, in one run.

    python benchmarks/bench_fixed_cost.py --data ../shared/data [--images 2] [--repeats 3]
        [--workdir /tmp/vprflow-fixed-cost] [--methods NAME ...]
    python benchmarks/bench_fixed_cost.py --smoke     # segvlad + mnn only, one repeat

The workflow runs on ``--images`` corridor images (half references, half queries: the
``bench_workflow.py`` set), corridor's methods and re-rankers, on one core, so that no
two jobs share the CPU. Per stage (``gather``: the sharded stages' gathers), the median
over its jobs of:

- ``job s``: Snakemake's ``benchmark:`` file (the whole job: Snakemake's spawn of the
  rule's script, the interpreter, its imports, opening the stores, the work); a gather
  has no such file, its column is its process's;
- ``process s``: from the interpreter's ``site`` import to its exit, as a
  ``sitecustomize`` module that this script puts on the jobs' ``PYTHONPATH`` records it;
- ``stage s``: inside ``run_stage`` (its log's ``resources:`` line): importing the
  stage's module and the libraries it computes with, opening the stores, the work;
- ``import s``: a fresh ``python -c "import snakemake.script, <the job's code>"``
  (``vprflow.stages.jobs``, ``runner`` and the stage's module; the interpreter's start
  included), fastest of ``--repeats``;
- ``libraries``: which of torch, transformers, faiss, cv2, matplotlib, skimage, scipy
  the job had imported when it ended.

``model``: the stage's module imports ``vprflow.models.loaders`` (features, segments).
``> 0.5 s`` marks a stage that loads no model and whose job took more than 0.5 s (the
guard of issue 50: at idle, no such stage above it, but for the jobs that compute with
torch, ~1.2 s to import: a VLAD method's PCA and descriptors, for the published
assignment, paid once per ``descriptors_shard_size`` images, and the matches). The first
rows are the pieces alone: ``python -c pass``, Snakemake's script preamble, and the heavy
libraries.

``--data`` defaults to ``$VPRFLOW_DATA``; with neither, ``--smoke`` exits with status 77
(skipped, as automake and meson count it), anything else with an error. A smoke times
two of the pieces (``pass`` and the preamble), not the three libraries.

With ``$VPRFLOW_SMOKE_RUN`` set (tests/repository/test_benchmarks.py sets it), ``--smoke`` reads the
one run that the smoke modes of bench_city.py, bench_workflow.py, bench_fixed_cost.py
and bench_descriptors.py share (smoke_run.py: bench_city.py's 16-image smoke city, on
one core) instead of making one of its own.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from vprflow.planning.plan import STAGES
from vprflow.stages import jobs
from vprflow.stages.jobs import RUNNERS

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_workflow import (  # noqa: E402
    RESOURCES,
    SMOKE_METHODS,
    SMOKE_RERANK,
    cycled_config,
    data_folder,
    run_snakemake,
    snakemake_command,
)
from smoke_run import shared_run  # noqa: E402

CORES = 1  # so that no two jobs share the CPU
GUARD = 0.5  # seconds: the most a job of a stage that loads no model may cost at idle
LIBRARIES = ("torch", "transformers", "faiss", "cv2", "matplotlib", "skimage", "scipy")

# Written to the jobs' PYTHONPATH: at exit, each script job of the run appends its stage,
# its process's seconds and the heavy libraries it imported (a job is a script with the
# `snakemake` object in its __main__; Snakemake's own processes have none).
SITECUSTOMIZE = """\
import atexit, json, os, sys, time

_started = time.perf_counter()


def _record():
    job = getattr(sys.modules.get("__main__"), "snakemake", None)
    if job is None:
        return
    entry = {{
        "rule": job.rule,
        "log": str(job.log[0]) if job.log else "",
        "process": time.perf_counter() - _started,
        "libraries": [name for name in {libraries!r} if name in sys.modules],
    }}
    with open({out!r}, "a") as f:
        f.write(json.dumps(entry) + "\\n")


atexit.register(_record)
"""

# The pieces of a job's start-up, each a fresh process: the floor, the script's preamble,
# and the heavy libraries a stage imports when it computes with them.
PIECES = ("pass", "import snakemake.script", "import torch", "import faiss", "import cv2")

IMPORTS = """\
import sys
import snakemake.script, vprflow.stages.jobs, vprflow.stages.runner, {module}
print("vprflow.models.loaders" in sys.modules)
"""


def stage_module(stage: str) -> str:
    """The module of the function a stage's runner calls; the gather's own."""
    if stage == "gather":
        return "vprflow.stages.gather"
    # The runner calls `<module>.<function>(job)`, the module one of jobs.py's lazy imports.
    return getattr(jobs, RUNNERS[stage].__code__.co_names[0]).__name__


def fastest(code: str, repeats: int) -> tuple[float, str]:
    """The fastest of ``repeats`` fresh ``python -c code`` (seconds) and its stdout."""
    best, out = float("inf"), ""
    for _ in range(repeats):
        start = time.perf_counter()
        result = subprocess.run(
            [sys.executable, "-c", code], check=True, capture_output=True, text=True
        )
        seconds = time.perf_counter() - start
        if seconds < best:
            best, out = seconds, result.stdout
    return best, out


def benchmark_seconds(workdir: Path) -> dict[str, float]:
    """Each job's Snakemake ``benchmark:`` wall seconds, by its log's path."""
    seconds = {}
    for path in (workdir / "logs").rglob("*.benchmark.tsv"):
        with open(path) as f:
            row = next(csv.DictReader(f, delimiter="\t"))
        log = path.with_name(path.name.removesuffix(".benchmark.tsv") + ".log")
        seconds[str(log.relative_to(workdir))] = float(row["s"])
    return seconds


def stage_seconds(log: Path) -> float | None:
    """The wall seconds of a log's ``resources:`` line (run_stage's), if it has one."""
    found = RESOURCES.findall(log.read_text(errors="replace")) if log.is_file() else []
    return float(found[-1][0]) if found else None


def recorded_run(workdir: Path, config_path: Path, target: str) -> None:
    """Snakemake to ``target`` in ``workdir`` on :data:`CORES` core, each stage job
    recorded (see SITECUSTOMIZE) to ``workdir/jobs.jsonl``."""
    site, jobs_file = workdir / "site", workdir / "jobs.jsonl"
    site.mkdir()
    (site / "sitecustomize.py").write_text(
        SITECUSTOMIZE.format(libraries=LIBRARIES, out=str(jobs_file))
    )
    paths = [str(site), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(paths)}
    run_snakemake(snakemake_command(workdir, config_path, CORES, target), env)


def run_jobs(args: argparse.Namespace, data: Path) -> list[dict]:
    """The workflow on the tiny set, one core (or the smoke run the benchmarks share,
    smoke_run.py); one entry per stage job (see SITECUSTOMIZE) with its ``job`` and
    ``stage`` seconds added."""
    shared = shared_run() if args.smoke else None
    if shared:
        args.workdir, args.images = shared[0], shared[1]["images"]
    else:
        if args.workdir.exists():
            shutil.rmtree(args.workdir)
        _, config_path = cycled_config(data, args.workdir, args.images, args.methods, args.rerank)
        recorded_run(args.workdir, config_path, "results/recall_cycled.csv")
    walls = benchmark_seconds(args.workdir)
    jobs_file = args.workdir / "jobs.jsonl"
    entries = [json.loads(line) for line in jobs_file.read_text().splitlines()]
    jobs = []
    for entry in entries:
        if entry["rule"] not in STAGES and entry["rule"] != "gather":
            continue  # the tables and the report: not stages
        entry["job"] = walls.get(entry["log"], entry["process"])
        entry["stage"] = stage_seconds(args.workdir / entry["log"])
        jobs.append(entry)
    return jobs


def report(args: argparse.Namespace, jobs: list[dict]) -> None:
    # A smoke times the two light pieces: the three libraries cost 2 s of CPU to import.
    pieces = {code: fastest(code, args.repeats)[0] for code in PIECES[: 2 if args.smoke else None]}
    header = (
        f"| {'stage':<26} | jobs | job s | process s | stage s | import s | model | "
        f"{'> 0.5 s':<7} | libraries |"
    )
    print(f"{args.images} images, {len(jobs)} stage jobs on 1 core; the median job per stage")
    print()
    print(header)
    print("| --- | ---: | ---: | ---: | ---: | ---: | --- | --- | --- |")
    for code, seconds in pieces.items():
        print(f"| {f'(python -c {code!r})':<26} | | {seconds:.2f} | | | | | | |")
    above = []
    for stage in [*STAGES, "gather"]:
        mine = [job for job in jobs if job["rule"] == stage]
        if not mine:
            continue
        imports, out = fastest(IMPORTS.format(module=stage_module(stage)), args.repeats)
        model = out.strip() == "True"
        job = statistics.median(j["job"] for j in mine)
        process = statistics.median(j["process"] for j in mine)
        inside = [j["stage"] for j in mine if j["stage"] is not None]
        libraries = sorted({name for j in mine for name in j["libraries"]})
        over = not model and job > GUARD
        if over:
            above.append(stage)
        print(
            f"| {stage:<26} | {len(mine):>4} | {job:.2f} | {process:.2f} | "
            f"{statistics.median(inside) if inside else float('nan'):.2f} | {imports:.2f} | "
            f"{'yes' if model else 'no':<5} | {'above' if over else '':<7} | "
            f"{', '.join(libraries) or '-'} |"
        )
    print()
    print(
        f"stages that load no model above {GUARD} s: {', '.join(above) or 'none'} "
        f"(load average {os.getloadavg()[0]:.2f})"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, help="folder holding corridor/ ($VPRFLOW_DATA)")
    parser.add_argument("--images", type=int, default=2, help="half references, half queries")
    parser.add_argument("--repeats", type=int, default=3, help="fresh imports, fastest of")
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/vprflow-fixed-cost"))
    parser.add_argument("--methods", nargs="+", help="of the config (default: corridor's)")
    parser.add_argument(
        "--smoke", action="store_true", help="segvlad + mnn only, one repeat, a temporary workdir"
    )
    parser.set_defaults(rerank=None)  # corridor's
    args = parser.parse_args()
    data = data_folder(parser, args)
    if not args.smoke:
        report(args, run_jobs(args, data))
        return
    args.repeats, args.methods, args.rerank = 1, SMOKE_METHODS, SMOKE_RERANK
    with tempfile.TemporaryDirectory(prefix="vprflow-fixed-cost-smoke-") as workdir:
        args.workdir = Path(workdir)
        report(args, run_jobs(args, data))


if __name__ == "__main__":
    main()
