"""The whole workflow on a synthetic N-image place set (the corridor images cycled),
timed per stage from Snakemake's ``benchmark:`` files.

    python benchmarks/bench_workflow.py --data ../shared/data [--images 2000]
        [--shard 256] [--cores 2] [--workdir /tmp/vprflow-bench]

Half the images are references, half queries (query i = reference i's corridor image
with another index, so every query has one positive by construction: VPR-Bench ground
truth listing reference i). The corridor config's five methods run at the corridor
resolution. Prints, per stage: jobs, total seconds, seconds per image and the largest
peak memory (max RSS) of any of its jobs; and the whole run's wall time.
"""

from __future__ import annotations

import argparse
import csv
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import yaml

REPO = Path(__file__).resolve().parents[1]


def make_set(source: Path, target: Path, n_images: int) -> None:
    """``target/{ref,query}`` of symlinks cycling ``source/{ref,query}``, and a truth."""
    refs = sorted((source / "ref").iterdir())
    queries = sorted((source / "query").iterdir())
    n_ref = n_query = n_images // 2
    for role, files, n in (("ref", refs, n_ref), ("query", queries, n_query)):
        (target / role).mkdir(parents=True, exist_ok=True)
        for i in range(n):
            link = target / role / f"{i:06d}{files[i % len(files)].suffix}"
            if not link.exists():
                link.symlink_to(files[i % len(files)].resolve())
    truth = np.empty((n_query, 2), dtype=object)
    for q in range(n_query):
        truth[q, 0], truth[q, 1] = q, [q]
    np.save(target / "ground_truth_new.npy", truth, allow_pickle=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="folder holding corridor/")
    parser.add_argument("--images", type=int, default=2000)
    parser.add_argument("--shard", type=int, default=256)
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/vprflow-bench"))
    args = parser.parse_args()

    if args.workdir.exists():
        shutil.rmtree(args.workdir)
    data = args.workdir / "data"
    make_set(args.data / "corridor", data / "cycled", args.images)
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    corridor = config["datasets"]["corridor"]
    config["data_root"] = str(data)
    config["shard_size"] = args.shard
    config["search_shard_size"] = args.shard
    config["datasets"] = {"cycled": {**corridor, "path": "cycled"}}
    config["targets"] = ["cycled"]
    config_path = args.workdir / "config.yaml"
    config_path.write_text(yaml.safe_dump(config))
    command = [
        sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "workflow" / "Snakefile"),
        "--directory", str(args.workdir), "--configfile", str(config_path),
        "--cores", str(args.cores), "results/recall_cycled.csv",
    ]  # fmt: skip
    start = time.perf_counter()
    subprocess.run(command, check=True, capture_output=True)
    wall = time.perf_counter() - start

    stats: dict[str, list[tuple[float, float]]] = {}
    for path in (args.workdir / "logs").rglob("*.benchmark.tsv"):
        stage = path.relative_to(args.workdir / "logs").parts[0]
        with open(path) as f:
            row = next(csv.DictReader(f, delimiter="\t"))
        stats.setdefault(stage, []).append((float(row["s"]), float(row["max_rss"])))
    print(f"{args.images} images (shard {args.shard}, {args.cores} cores): {wall:.0f} s wall")
    print(f"{'stage':<12} {'jobs':>5} {'seconds':>9} {'s/image':>9} {'peak MiB':>9}")
    for stage, rows in sorted(stats.items()):
        total = sum(s for s, _ in rows)
        peak = max(m for _, m in rows)
        print(f"{stage:<12} {len(rows):>5} {total:>9.1f} {total / args.images:>9.4f} {peak:>9.0f}")


if __name__ == "__main__":
    main()
