"""The numbers README.md quotes, measured: the install's time, the corridor run's wall
time and CPU seconds, and corridor's SegVLAD Recall@1 with the shipped PCA and with the
published one; each printed beside the README's value.

    python benchmarks/bench_readme.py --data ../shared/data [--install] [--reuse DIR]
    python benchmarks/bench_readme.py --smoke     # the README's values only, nothing run

The corridor run is the README's first command (`snakemake --cores 2 --config
data_root=...`, the shipped config) in a fresh temporary work folder: its wall time, the
CPU seconds of Snakemake and every job it started (``getrusage`` of the children), the
sum of the stage jobs' own CPU seconds (their logs) and the load average before and
after, since the wall time grows with whatever else the machine runs. ``--reuse DIR``
reads a finished run's table and logs instead (no wall time). Then SegVLAD alone with the
published PCA (1024 whitened components) in the same folder, which reruns its PCA,
descriptors, search and recall only. ``--install`` also times the README's install line
(``pip install "torch==2.13.0" && pip install -e ".[dev]"``) into a fresh virtual
environment: a download-bound time that depends on the network and pip's cache.

``tests/repository/test_readme_numbers.py`` checks the Recall@1 values against the test suite's
own corridor run; the times have no test (they depend on the machine): rerun this script
when a change moves them.
"""

from __future__ import annotations

import argparse
import csv
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).parent))
from bench_workflow import (  # noqa: E402
    REPO,
    benchmark_rows,
    data_folder,
    run_snakemake,
    snakemake_command,
)

# What README.md says, one pattern per number (the groups are the numbers), so that a
# rewording that drops one fails --smoke instead of leaving it unchecked.
QUOTES = {
    "install_minutes": r"installs vprflow \([^)]*?(\d+) to (\d+) minutes",
    "corridor_cpu_seconds": r"corridor` dataset from `\.\./shared/data` \(about (\d+) CPU seconds",
    "corridor_wall_seconds": r"(\d+) s measured on 2 CPU cores at a load average of",
    "segvlad_r1_published_pca": r"corridor SegVLAD R@1 (0\.\d+) instead of",
    "segvlad_r1_shipped_pca": r"corridor SegVLAD R@1 0\.\d+ instead of (0\.\d+)",
}


def readme_quotes(text: str) -> dict[str, tuple[float, ...]]:
    """Each of :data:`QUOTES`' numbers as README.md's ``text`` gives them."""
    found = {}
    for name, pattern in QUOTES.items():
        match = re.search(pattern, " ".join(text.split()))
        if match is None:
            raise ValueError(f"README.md no longer says {name} (pattern {pattern!r})")
        found[name] = tuple(float(v) for v in match.groups())
    return found


def published_pca_config(config: dict) -> dict:
    """The shipped ``config``'s corridor entry with the published PCA (the top-level
    `pca`'s size and whitening), SegVLAD alone and not re-ranked: the README's comparison.
    Written for `--configfile`, which Snakemake merges over config/config.yaml, so each
    change is a value, not a dropped key."""
    pca = {key: config["pca"][key] for key in ("dim", "whiten")}
    corridor = {
        **config["datasets"]["corridor"],
        "defaults": {"pca": pca},
        "methods": ["segvlad"],
        "rerank": {"segvlad": []},
    }
    return {**config, "datasets": {**config["datasets"], "corridor": corridor}}


def recall_at_1(table: Path, method: str) -> float:
    with open(table) as f:
        rows = {row["method"]: row for row in csv.DictReader(f)}
    return float(rows[method]["recall@1"])


def children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def timed_snakemake(command: list[str]) -> tuple[float, float]:
    """``(wall seconds, CPU seconds of Snakemake and every process it started)``."""
    cpu, start = children_cpu(), time.perf_counter()
    run_snakemake(command)
    return time.perf_counter() - start, children_cpu() - cpu


def time_install(folder: Path) -> float:
    """Wall seconds of the README's install line into a fresh virtual environment."""
    subprocess.run([sys.executable, "-m", "venv", str(folder)], check=True)
    pip = [str(folder / "bin" / "python"), "-m", "pip", "install", "--quiet"]
    start = time.perf_counter()
    subprocess.run([*pip, "torch==2.13.0"], check=True)
    subprocess.run([*pip, "-e", f"{REPO}[dev]"], check=True, cwd=REPO)
    return time.perf_counter() - start


def write_config(workdir: Path, config: dict, name: str) -> Path:
    path = workdir / name
    path.write_text(yaml.safe_dump(config))
    return path


def measure(args: argparse.Namespace, data: Path, workdir: Path) -> dict[str, str]:
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config["data_root"] = str(data)
    measured = {}
    if args.reuse is None:
        load = os.getloadavg()[0]
        command = snakemake_command(workdir, write_config(workdir, config, "shipped.yaml"), 2)
        wall, cpu = timed_snakemake(command)
        measured["corridor_wall_seconds"] = (
            f"{wall:.0f} s wall (load average {load:.1f} before, {os.getloadavg()[0]:.1f} after)"
        )
        measured["corridor_cpu_seconds"] = f"{cpu:.0f} CPU s (Snakemake and every job)"
    stages = benchmark_rows(workdir)
    jobs = sum(len(rows) for rows in stages.values())
    stage_cpu = sum(job.cpu for rows in stages.values() for job in rows)
    measured["corridor_stage_cpu"] = f"{stage_cpu:.0f} CPU s in the {jobs} stage jobs"
    table = workdir / "results" / "recall_corridor.csv"
    measured["segvlad_r1_shipped_pca"] = f"{recall_at_1(table, 'segvlad'):.3f}"
    published = write_config(workdir, published_pca_config(config), "published_pca.yaml")
    run_snakemake(snakemake_command(workdir, published, 2, "--", "results/recall_corridor.csv"))
    measured["segvlad_r1_published_pca"] = f"{recall_at_1(table, 'segvlad'):.3f}"
    if args.install:
        with tempfile.TemporaryDirectory(prefix="vprflow-install-") as venv:
            measured["install_minutes"] = f"{time_install(Path(venv)) / 60:.1f} min"
    return measured


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, help="folder holding corridor/ ($VPRFLOW_DATA)")
    parser.add_argument("--install", action="store_true", help="also time the install line")
    parser.add_argument("--reuse", type=Path, help="a finished corridor run's work folder")
    parser.add_argument("--smoke", action="store_true", help="README.md's values, nothing run")
    args = parser.parse_args()
    quotes = readme_quotes((REPO / "README.md").read_text())
    measured: dict[str, str] = {}
    if not args.smoke:
        data = data_folder(parser, args)
        if args.reuse is None:
            with tempfile.TemporaryDirectory(prefix="vprflow-readme-") as workdir:
                measured = measure(args, data, Path(workdir))
        else:
            copy = Path(tempfile.mkdtemp(prefix="vprflow-readme-"))
            try:  # a copy: the published-PCA run rewrites the table
                shutil.copytree(args.reuse, copy, symlinks=True, dirs_exist_ok=True)
                measured = measure(args, data, copy)
            finally:
                shutil.rmtree(copy)
    names = list(dict.fromkeys([*quotes, *measured]))
    print(f"{'number':<26} {'README.md':>12}  measured")
    print("-" * 70)
    for name in names:
        quoted = " to ".join(f"{v:g}" for v in quotes.get(name, ())) or "-"
        print(f"{name:<26} {quoted:>12}  {measured.get(name, '-')}")


if __name__ == "__main__":
    main()
