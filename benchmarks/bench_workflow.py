"""The whole workflow on a synthetic N-image place set (the corridor images cycled),
timed per stage from Snakemake's ``benchmark:`` files.

    python benchmarks/bench_workflow.py --data ../shared/data [--images 2000]
        [--shard 256] [--cores 2] [--workdir /tmp/vprflow-bench] [--methods NAME ...]
    python benchmarks/bench_workflow.py --smoke     # 4 images, shard 2, segvlad + mnn only

Half the images are references, half queries (query i = reference i's corridor image
with another index, so every query has one positive by construction: VPR-Bench ground
truth listing reference i). The corridor config's five methods (or ``--methods``) run
at the corridor resolution, ``--shard`` images a job of features, segments and search,
descriptors in the shipped config's ``descriptors_shard_size``. Prints, per stage: jobs,
total seconds, seconds per image and the largest peak memory (max RSS) of any of its
jobs; and the whole run's wall time.

``--data`` defaults to ``$VPRFLOW_DATA``; with neither, ``--smoke`` exits with status 77
(skipped, as automake and meson count it), anything else with an error.

With ``$VPRFLOW_SMOKE_RUN`` set (tests/repository/test_benchmarks.py sets it), ``--smoke`` reads the
one run that the smoke modes of bench_city.py, bench_workflow.py, bench_fixed_cost.py
and bench_descriptors.py share (smoke_run.py: bench_city.py's 16-image smoke city, on
one core) instead of making one of its own.
"""

from __future__ import annotations

import argparse
import csv
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np
import yaml

from vprflow.stages import runner

sys.path.insert(0, str(Path(__file__).resolve().parent))
from smoke_run import shared_run  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
# The exit status test harnesses (automake, meson, tests/repository/test_benchmarks.py) skip.
SKIPPED = 77
# The smoke runs' methods (this script's, bench_fixed_cost.py's, bench_city.py's): one that
# runs every stage, re-ranked by one re-ranker; each job costs a Python start-up.
SMOKE_METHODS, SMOKE_RERANK = ["segvlad"], {"segvlad": ["mnn"]}


def make_set(source: Path, target: Path, n_images: int) -> None:
    """``target/{ref,query}`` of copies cycling ``source/{ref,query}``, and a truth.

    Copies, not links: a dataset refuses links out of its folder, and a file reached
    twice through links, which cycling makes (corridor has 111 images per side)."""
    refs = sorted((source / "ref").iterdir())
    queries = sorted((source / "query").iterdir())
    n_ref = n_query = n_images // 2
    for role, files, n in (("ref", refs, n_ref), ("query", queries, n_query)):
        (target / role).mkdir(parents=True, exist_ok=True)
        for i in range(n):
            copy = target / role / f"{i:06d}{files[i % len(files)].suffix}"
            if not copy.exists():
                shutil.copyfile(files[i % len(files)], copy)
    truth = np.empty((n_query, 2), dtype=object)
    for q in range(n_query):
        truth[q, 0], truth[q, 1] = q, [q]
    np.save(target / "ground_truth_new.npy", truth, allow_pickle=True)


def cycled_config(
    data: Path,
    workdir: Path,
    n_images: int,
    methods: list[str] | None = None,
    rerank: dict | None = None,
    **settings,
) -> tuple[dict, Path]:
    """The shipped config with its corridor entry as the only dataset, ``cycled``, over
    ``n_images`` corridor images cycled under ``workdir/data``, with corridor's methods
    and re-rankers or ``methods`` and ``rerank``; written to ``workdir/config.yaml``.
    ``settings`` are further top-level keys."""
    make_set(data / "corridor", workdir / "data" / "cycled", n_images)
    changes = {"path": "cycled"} | ({"methods": methods} if methods else {})
    changes |= {"rerank": rerank} if rerank else {}
    return one_dataset_config(workdir, workdir / "data", "cycled", changes, **settings)


def one_dataset_config(
    workdir: Path, data_root: Path, name: str, changes: dict, **settings
) -> tuple[dict, Path]:
    """The shipped config with one dataset, ``name``: its corridor entry (methods,
    re-rankers, resolution, defaults) with ``changes`` put over it, under ``data_root``;
    the only target. ``settings`` are further top-level keys. Written to
    ``workdir/config.yaml``."""
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config["data_root"] = str(data_root)
    config["datasets"] = {name: {**config["datasets"]["corridor"], **changes}}
    config["targets"] = [name]
    config.update(settings)
    workdir.mkdir(parents=True, exist_ok=True)
    config_path = workdir / "config.yaml"
    config_path.write_text(yaml.safe_dump(config))
    return config, config_path


def snakemake_command(workdir: Path, config_path: Path, cores: int, *targets: str) -> list[str]:
    """The workflow's Snakemake run in ``workdir`` on ``config_path``."""
    return [
        sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "workflow" / "Snakefile"),
        "--directory", str(workdir), "--configfile", str(config_path),
        "--cores", str(cores), *targets,
    ]  # fmt: skip


class Job(NamedTuple):
    """One job's line of its Snakemake ``benchmark:`` file, CPU and peak memory from its
    log's ``resources:`` line where it has one."""

    seconds: float  # wall time
    max_rss: float  # MiB
    cpu: float  # CPU seconds (user + system) of the job's processes: less sensitive to load
    exact: bool  # cpu and max_rss from the log (else Snakemake's samples, every 30 s)


# run_stage's last log line, its format's numbers as groups: wall, CPU, peak RSS.
RESOURCES = re.compile(re.sub(r"%\\\.\df", r"([\\d.]+)", re.escape(runner.RESOURCES)))


def benchmark_rows(workdir: Path) -> dict[str, list[Job]]:
    """Per stage, each job's :class:`Job` from Snakemake's ``benchmark:`` files
    (``logs/<stage>/<key>/<part>.benchmark.tsv``) and logs (``<part>.log``).

    Snakemake samples a job's CPU every 30 s, so its ``cpu_time`` misses up to the last
    30 s of the job's threads; a log written by ``run_stage`` states the exact figure."""
    stats: dict[str, list[Job]] = {}
    for path in sorted((workdir / "logs").rglob("*.benchmark.tsv")):
        stage = path.relative_to(workdir / "logs").parts[0]
        with open(path) as f:
            row = next(csv.DictReader(f, delimiter="\t"))
        log = path.with_name(path.name.removesuffix(".benchmark.tsv") + ".log")
        found = RESOURCES.findall(log.read_text(errors="replace")) if log.is_file() else []
        if found:
            _, cpu, peak = found[-1]
            job = Job(float(row["s"]), float(peak), float(cpu), True)
        else:
            job = Job(float(row["s"]), float(row["max_rss"]), float(row["cpu_time"]), False)
        stats.setdefault(stage, []).append(job)
    return stats


def data_folder(parser: argparse.ArgumentParser, args: argparse.Namespace) -> Path:
    """``--data`` or ``$VPRFLOW_DATA``; without either, a smoke run is skipped."""
    value = args.data or os.environ.get("VPRFLOW_DATA")
    if not value or not (Path(value) / "corridor").is_dir():
        message = f"needs the folder holding corridor/ (--data or $VPRFLOW_DATA; got {value!r})"
        if args.smoke:
            print(f"skipped: {message}")
            sys.exit(SKIPPED)
        parser.error(message)
    return Path(value).resolve()


def run_snakemake(command: list[str], env: dict | None = None) -> None:
    """Run Snakemake quietly (in ``env``, default this process's environment); on failure
    show the end of its output and exit with its status (a CalledProcessError would drop
    the output that says why)."""
    result = subprocess.run(command, capture_output=True, text=True, env=env)
    if result.returncode:
        print("\n".join((result.stdout + result.stderr).splitlines()[-40:]), file=sys.stderr)
        sys.exit(f"snakemake failed (status {result.returncode})")


def run(args: argparse.Namespace, data: Path) -> None:
    shared = shared_run() if args.smoke else None
    if shared:  # the smoke run the benchmarks share (smoke_run.py)
        workdir, record = shared
        print_table(workdir, record["images"], record["shards"], record["cores"], record["wall"])
        return
    if args.workdir.exists():
        shutil.rmtree(args.workdir)
    config, config_path = cycled_config(
        data,
        args.workdir,
        args.images,
        args.methods,
        args.rerank,
        shard_size=args.shard,
        search_shard_size=args.shard,
    )
    command = snakemake_command(args.workdir, config_path, args.cores, "results/recall_cycled.csv")
    start = time.perf_counter()
    run_snakemake(command)
    wall = time.perf_counter() - start

    shards = f"shard {args.shard}, descriptors {config['descriptors_shard_size']}"
    print_table(args.workdir, args.images, shards, args.cores, wall)


def print_table(workdir: Path, images: int, shards: str, cores: int, wall: float) -> None:
    """Per stage of the finished run in ``workdir``: jobs, seconds, per image, peak."""
    stats = benchmark_rows(workdir)
    print(f"{images} images ({shards}, {cores} cores): {wall:.0f} s wall")
    header = f"{'stage':<12} {'jobs':>5} {'seconds':>9} {'s/image':>9} {'peak MiB':>9}"
    print(header)
    print("-" * len(header))
    for stage, rows in sorted(stats.items()):
        total = sum(job.seconds for job in rows)
        peak = max(job.max_rss for job in rows)
        print(f"{stage:<12} {len(rows):>5} {total:>9.1f} {total / images:>9.4f} {peak:>9.0f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, help="folder holding corridor/ ($VPRFLOW_DATA)")
    parser.add_argument("--images", type=int, default=2000)
    parser.add_argument("--shard", type=int, default=256)
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/vprflow-bench"))
    parser.add_argument("--methods", nargs="+", help="of the config (default: corridor's)")
    parser.add_argument(
        "--smoke", action="store_true", help="4 images, shard 2, segvlad + mnn, a temporary workdir"
    )
    parser.set_defaults(rerank=None)  # corridor's
    args = parser.parse_args()
    data = data_folder(parser, args)
    if not args.smoke:
        run(args, data)
        return
    # Two shards a sharded stage, as the full run has many.
    args.images, args.shard, args.methods, args.rerank = 4, 2, SMOKE_METHODS, SMOKE_RERANK
    with tempfile.TemporaryDirectory(prefix="vprflow-bench-smoke-") as workdir:
        args.workdir = Path(workdir)
        run(args, data)


if __name__ == "__main__":
    main()
