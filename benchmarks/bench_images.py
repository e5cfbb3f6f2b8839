"""What reading an image costs with the checks that keep a table honest.

    python benchmarks/bench_images.py                  # corridor (if found) and synthetic sizes
    python benchmarks/bench_images.py --repeat 3 --sizes 640x480
    python benchmarks/bench_images.py --smoke          # one pass, 4 synthetic 160 x 120 images

Per query image, median over ``--repeat`` passes, milliseconds:

- ``decode``: ``images.read_image`` (PIL decode, EXIF orientation, float conversion);
- ``sha256``: hashing the file's bytes, the check ``Dataset.read_image`` adds before it
  decodes (a file changed during a run must fail, not be computed under its old key);
- ``checked``: ``Dataset.read_image`` as the stages call it (read, hash, decode), on a
  dataset store the dataset stage built (its job through ``vprflow.stages.jobs``, as
  the ``dataset`` rule runs it);
- ``scan``: ``images.scan_images`` of the query folder, per image (links, formats, order).

Images: the corridor dataset under ``$VPRFLOW_DATA`` when it is there, and synthetic
JPEGs of ``--sizes`` (textured noise, quality 90) written to a temporary folder, with
one reference image of other noise beside them (a dataset needs both roles).
"""

from __future__ import annotations

import argparse
import hashlib
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

from vprflow.data.images import read_image, scan_images
from vprflow.planning.config import validate_config
from vprflow.planning.plan import build_plan
from vprflow.stages.jobs import Job, run_job
from vprflow.stages.readers import Dataset

REPO = Path(__file__).resolve().parents[1]


def per_image_ms(function, items: list, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        for item in items:
            function(item)
        times.append((time.perf_counter() - start) / len(items) * 1e3)
    return statistics.median(times)


def synthetic(folder: Path, width: int, height: int, count: int, seed: int = 0) -> list[Path]:
    folder.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    paths = []
    for i in range(count):
        noise = rng.integers(0, 256, (height // 8, width // 8, 3), dtype=np.uint8)
        image = Image.fromarray(noise).resize((width, height), Image.Resampling.BILINEAR)
        path = folder / f"{i:04d}.jpg"
        image.save(path, quality=90)
        paths.append(path)
    return paths


def dataset_store(data_root: Path, folder: str, out: Path) -> Dataset:
    """``data_root/folder/{ref,query}`` as the images stage stores it, opened as the
    later stages open it: the shipped config with this folder as its one dataset."""
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config["data_root"] = str(data_root)
    config["targets"] = []
    entry = {"path": folder, "reference": "ref", "query": "query", "resolution": [160, 120]}
    entry |= {"ground_truth": {"kind": "none"}, "methods": [next(iter(config["methods"]))]}
    config["datasets"] = {"bench": entry}
    config = validate_config(config, REPO / "workflow" / "schemas" / "config.schema.yaml")
    plan = build_plan(config)
    stage = plan.stages["images"][plan.images_keys["bench"]]
    run_job(Job(stage.record, {}, str(out), data_root=str(data_root)))
    return Dataset(str(out), str(data_root))


def measure(name: str, dataset: Dataset, repeat: int) -> tuple:
    queries = list(dataset.indices("query"))
    paths = [Path(dataset.paths[i]) for i in queries]
    decode = per_image_ms(read_image, paths, repeat)
    sha = per_image_ms(lambda p: hashlib.sha256(p.read_bytes()).hexdigest(), paths, repeat)
    full = per_image_ms(dataset.read_image, queries, repeat)
    folder = paths[0].parent
    scan = per_image_ms(lambda _: scan_images(folder), [folder], repeat) / len(paths)
    size = np.mean([p.stat().st_size for p in paths]) / 1024
    return name, len(paths), size, decode, sha, full, 100 * (full - decode) / decode, scan


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--sizes", nargs="*", default=["160x120", "640x480", "4032x3024"])
    parser.add_argument("--count", type=int, default=20, help="synthetic images per size")
    parser.add_argument(
        "--smoke", action="store_true", help="one pass, corridor and 4 synthetic 160 x 120 images"
    )
    args = parser.parse_args()
    if args.smoke:
        args.repeat, args.sizes, args.count = 1, ["160x120"], 4
    datasets = []
    data = os.environ.get("VPRFLOW_DATA")
    corridor = Path(data) / "corridor" if data else None
    with tempfile.TemporaryDirectory() as tmp:
        if corridor and (corridor / "query").is_dir():
            store = Path(tmp) / "corridor.zarr"
            datasets.append(("corridor query", dataset_store(corridor.parent, "corridor", store)))
        for size in args.sizes:
            width, height = (int(v) for v in size.split("x"))
            synthetic(Path(tmp) / size / "ref", width, height, 1, seed=1)
            synthetic(Path(tmp) / size / "query", width, height, args.count)
            store = Path(tmp) / f"{size}.zarr"
            datasets.append((f"jpeg {size}", dataset_store(Path(tmp), size, store)))
        rows = [measure(name, dataset, args.repeat) for name, dataset in datasets]
    header = "images | n | KiB/file | decode ms | sha256 ms | checked ms | check cost | scan ms"
    print(header)
    print("|".join(["---"] * 8))
    for name, n, kib, decode, sha, full, cost, scan in rows:
        print(
            f"{name} | {n} | {kib:.1f} | {decode:.3f} | {sha:.3f} | {full:.3f} | "
            f"{cost:+.1f}% | {scan:.4f}"
        )


if __name__ == "__main__":
    main()
