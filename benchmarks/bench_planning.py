"""Planning at scale: `snakemake -n` and `build_plan` on a dataset of many image files.

    python benchmarks/bench_planning.py                  # 100,000 files (Pitts250k-sized)
    python benchmarks/bench_planning.py --files 20000
    python benchmarks/bench_planning.py --smoke          # 500 files, seconds

Writes a synthetic `pitts250k` preset folder in the downloader's layout
(`images/test/{database,queries}`, half each, `@easting@northing@...@.jpg` names; every
file a tiny JPEG with distinct bytes) and a config that runs the preset with the
weight-free DAISY backbone and SLIC segments (AnyLoc-VLAD and SegVLAD). Then times, each
the best of `--repeats`:

- `snakemake -n results/recall_pitts250k.csv` cold (no fingerprint memo: every file is
  hashed) and warm (the memo of the cold run: files are listed and stat'ed, not read);
  the OS file cache is warm either way, so cold measures hashing, not the disk;
- `build_plan` alone in this process, warm.

The memo's size on disk is printed too. Files are tiny, so hashing real images costs
more: SHA-256 runs at about 1.5 GB/s on one core (`bench_images.py` has per-image costs).
"""

from __future__ import annotations

import argparse
import io
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

REPO = Path(__file__).resolve().parents[1]
SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"
TARGET = "results/recall_pitts250k.csv"


def write_dataset(root: Path, n_files: int) -> None:
    buffer = io.BytesIO()
    pixels = np.random.default_rng(0).integers(0, 255, (24, 32, 3), dtype=np.uint8)
    Image.fromarray(pixels).save(buffer, "JPEG")
    jpeg = buffer.getvalue()
    for role, count in (("database", n_files // 2), ("queries", n_files - n_files // 2)):
        folder = root / "images" / "test" / role
        folder.mkdir(parents=True, exist_ok=True)
        for i in range(count):
            east, north = 584000 + (i % 1000) * 3.0, 4477000 + (i // 1000) * 3.0
            name = f"@{east:.2f}@{north:.2f}@17@T@40.44@-79.99@{role[0]}{i:06d}@@@@@@@@.jpg"
            # Bytes after the JPEG's end marker make every file's content distinct.
            (folder / name).write_bytes(jpeg + i.to_bytes(4, "little"))


def write_config(workdir: Path, data_root: Path) -> Path:
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config["data_root"] = str(data_root)
    config["targets"] = []
    config["datasets"]["pitts250k"] = {
        "methods": ["anyloc_vlad", "segvlad"],
        "defaults": {"features": "daisy", "segmenter": "slic"},
    }
    path = workdir / "config.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def dry_run(workdir: Path, config: Path) -> float:
    command = [
        sys.executable,
        "-m",
        "snakemake",
        TARGET,
        "-n",
        "--cores",
        "1",
        "--snakefile",
        str(REPO / "workflow" / "Snakefile"),
        "--configfile",
        str(config),
    ]
    start = time.perf_counter()
    result = subprocess.run(command, cwd=workdir, capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    if result.returncode != 0:
        sys.exit(f"snakemake -n failed:\n{result.stdout[-2000:]}\n{result.stderr[-3000:]}")
    return elapsed


def plan_seconds(workdir: Path, config: Path) -> float:
    from vprflow.core.paths import FINGERPRINTS
    from vprflow.planning.config import validate_config
    from vprflow.planning.fingerprints import load_fingerprints
    from vprflow.planning.plan import build_plan

    validated = validate_config(yaml.safe_load(config.read_text()), SCHEMA)
    memo = load_fingerprints(str(workdir / FINGERPRINTS))
    start = time.perf_counter()
    plan = build_plan(validated, memo)
    elapsed = time.perf_counter() - start
    assert plan.dataset_keys["pitts250k"], "the synthetic dataset was not planned"
    return elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--files", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--smoke", action="store_true", help="500 files, one repeat")
    args = parser.parse_args()
    if args.smoke:
        args.files, args.repeats = 500, 1
    from vprflow.core.paths import FINGERPRINTS

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        start = time.perf_counter()
        write_dataset(tmp / "data" / "pitts250k", args.files)
        written = time.perf_counter() - start
        config = write_config(tmp, tmp / "data")
        cold, warm = [], []
        for _ in range(args.repeats):
            shutil.rmtree(tmp / "results", ignore_errors=True)
            shutil.rmtree(tmp / ".snakemake", ignore_errors=True)
            cold.append(dry_run(tmp, config))
            warm.append(dry_run(tmp, config))
        plan = min(plan_seconds(tmp, config) for _ in range(args.repeats))
        memo_mb = (tmp / FINGERPRINTS).stat().st_size / 1e6
    print(f"{args.files:,} image files (written in {written:.1f} s), best of {args.repeats}")
    print(f"{'measure':<32} {'seconds':>8}")
    print("-" * 41)
    print(f"{'snakemake -n, cold (no memo)':<32} {min(cold):>8.2f}")
    print(f"{'snakemake -n, warm (memo)':<32} {min(warm):>8.2f}")
    print(f"{'build_plan alone, warm':<32} {plan:>8.2f}")
    print(f"{'memo file (MB)':<32} {memo_mb:>8.1f}")


if __name__ == "__main__":
    main()
