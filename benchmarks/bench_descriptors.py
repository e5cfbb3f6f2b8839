"""Per-image time of the descriptors stage against the arithmetic it does, per method.

    python benchmarks/bench_descriptors.py --data ../shared/data [--images 256]
        [--threads 2] [--repeats 3] [--workdir /tmp/vprflow-bench-descriptors]

Builds the descriptors stage's inputs (dataset, DAISY features, SLIC segments,
vocabulary, PCA) for a synthetic N-image set (the corridor images cycled, as
bench_workflow.py) with Snakemake, once per work directory. Then, per method of the
corridor config, in one process and under the rule's thread budget (``run_stage``):

- stage: ``compute_descriptors`` over all images (store reads, PCA, writes, zarr);
- arithmetic: the method's per-image ``compute`` (and PCA transform) on every image's
  inputs read beforehand (float32 features, unpacked masks), one image at a time, with
  one BLAS thread or the rule's threads, whichever is faster;
- read: reading every image's inputs through the stage's readers alone;
- job: a fresh Python process running the stage as the rule's script does (imports,
  stage, store), as Snakemake's benchmark file would time it, less Snakemake's own
  script preamble.

Each is the best of ``--repeats`` runs, in ms per image; "ratio" = stage / arithmetic,
"job ratio" = job / arithmetic.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_workflow import REPO, make_set  # noqa: E402

from vprflow import stores  # noqa: E402
from vprflow.config import validate_config  # noqa: E402
from vprflow.plan import build_plan  # noqa: E402
from vprflow.runner import run_stage  # noqa: E402


def prepare(data: Path, workdir: Path, n_images: int):
    """The corridor config on the cycled set, its plan, and the descriptors stages,
    their inputs built by Snakemake in ``workdir``."""
    make_set(data / "corridor", workdir / "data" / "cycled", n_images)
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    corridor = config["datasets"]["corridor"]
    config["data_root"] = str(workdir / "data")
    config["datasets"] = {"cycled": {**corridor, "path": "cycled"}}
    config_path = workdir / "config.yaml"
    config_path.write_text(yaml.safe_dump(config))
    config = validate_config(config, REPO / "workflow" / "schemas" / "config.schema.yaml")
    plan = build_plan(config)
    targets = sorted(
        {p for s in plan.stages["descriptors"].values() for p in s.input_paths().values()}
    )
    missing = [t for t in targets if not (workdir / t).exists()]
    if missing:
        command = [
            sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "workflow" / "Snakefile"),
            "--directory", str(workdir), "--configfile", str(config_path), "--cores", "2",
            *missing,
        ]  # fmt: skip
        subprocess.run(command, check=True, capture_output=True)
    return plan


def best_of(function, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return min(times)


def method_name(stage) -> str:
    params = stage.params["params"]
    name = params["aggregator"]
    if name == "segvlad":
        name += f" order {params['order']}" + (" + pca" if "pca" in stage.inputs else "")
    return name


JOB = """
import json, sys
from vprflow.runner import run_stage
from vprflow.stages.descriptors import compute_descriptors
inputs, params, out, threads = json.loads(sys.argv[1])
run_stage("/dev/null", lambda: compute_descriptors(inputs, params, out, threads=threads), threads)
"""


def measure(stage, workdir: Path, repeats: int, threads: int) -> tuple[float, ...]:
    """(stage, arithmetic, read, job) seconds per image of one descriptors stage."""
    from vprflow.registry import aggregator
    from vprflow.stages.dataset import Dataset
    from vprflow.stages.descriptors import compute_descriptors
    from vprflow.stages.features import FeatureReader
    from vprflow.stages.pca import read_pca
    from vprflow.stages.segments import MaskReader

    inputs = {name: str(workdir / path) for name, path in stage.input_paths().items()}
    n = Dataset(inputs["dataset"]).n_images
    out = Path(tempfile.mkdtemp(dir=workdir)) / "descriptors.zarr"
    stage_s = best_of(
        lambda: compute_descriptors(inputs, stage.params, str(out), threads=threads), repeats
    )

    # The same per-image arithmetic on every image's inputs read beforehand.
    spec = stage.params["params"]
    describe = aggregator(spec["aggregator"]).descriptor_function(spec, inputs)
    data = [describe.read(i) for i in range(n)]
    pca = read_pca(inputs["pca"]) if "pca" in inputs else None

    def arithmetic():
        for item in data:
            rows = describe.compute(*item)
            if pca is not None:
                pca.transform(rows if rows.ndim == 2 else rows[None])

    # At its best: with one BLAS thread or with the rule's threads, whichever is faster.
    with threadpool_limits(limits=1):
        arithmetic_s = best_of(arithmetic, repeats)
    arithmetic_s = min(arithmetic_s, best_of(arithmetic, repeats))

    def read():
        reader = FeatureReader(stores.open_store(inputs["features"]))
        for i in range(n):
            reader(i)
        if "segments" in inputs:
            mask_reader = MaskReader(stores.open_store(inputs["segments"]))
            for i in range(n):
                mask_reader(i)

    read_s = best_of(read, repeats)
    job = json.dumps([inputs, stage.params, str(out), threads])
    job_s = best_of(lambda: subprocess.run([sys.executable, "-c", JOB, job], check=True), repeats)
    shutil.rmtree(out.parent)
    return stage_s / n, arithmetic_s / n, read_s / n, job_s / n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="folder holding corridor/")
    parser.add_argument("--images", type=int, default=256)
    parser.add_argument("--threads", type=int, default=2, help="the rule's thread budget")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/vprflow-bench-descriptors"))
    parser.add_argument("--methods", nargs="*", help="only these (e.g. 'segvlad order 3 + pca')")
    args = parser.parse_args()
    workdir = args.workdir.resolve() / str(args.images)
    workdir.mkdir(parents=True, exist_ok=True)
    plan = prepare(args.data.resolve(), workdir, args.images)
    stages = sorted(plan.stages["descriptors"].values(), key=method_name)
    rows = []

    def run_all():
        for stage in stages:
            name = method_name(stage)
            if not args.methods or name in args.methods:
                rows.append((name, *measure(stage, workdir, args.repeats, args.threads)))

    run_stage(os.devnull, run_all, args.threads)
    print(f"{args.images} corridor images, {args.threads} threads, best of {args.repeats}")
    print(
        f"{'method':<24} {'arith ms':>9} {'stage ms':>9} {'ratio':>6} {'read ms':>8} "
        f"{'job ms':>8} {'job ratio':>9}"
    )
    for name, stage_s, arithmetic_s, read_s, job_s in rows:
        print(
            f"{name:<24} {arithmetic_s * 1e3:>9.2f} {stage_s * 1e3:>9.2f} "
            f"{stage_s / arithmetic_s:>6.2f} {read_s * 1e3:>8.2f} {job_s * 1e3:>8.2f} "
            f"{job_s / arithmetic_s:>9.2f}"
        )


if __name__ == "__main__":
    main()
