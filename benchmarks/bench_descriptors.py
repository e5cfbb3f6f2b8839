"""Per-image time of the descriptors stage against the arithmetic it does, per method.

    python benchmarks/bench_descriptors.py --data ../shared/data [--images 256]
        [--threads 2] [--repeats 3] [--workdir /tmp/vprflow-bench-descriptors]
    python benchmarks/bench_descriptors.py --smoke   # 8 images, anyloc_vlad and segvlad

``--data`` defaults to ``$VPRFLOW_DATA`` (a smoke run without either is skipped, status
77, as in bench_workflow.py).

Builds the descriptors stage's inputs (dataset, DAISY features, SLIC segments,
vocabulary, PCA) for a synthetic N-image set (the corridor images cycled, as
bench_workflow.py) with Snakemake, once per work directory. Then, per method of the
corridor config, in one process and under the rule's thread budget (``run_stage``):

- stage: the descriptors stage's job (``vprflow.stages.jobs.run_job``) over all images
  (store reads, PCA, writes, zarr);
- arithmetic: the method's per-image ``compute`` (and PCA transform) on every image's
  inputs read beforehand (float32 features, unpacked masks), one image at a time, with
  one BLAS thread or the rule's threads, whichever is faster;
- read: reading every image's inputs through the stage's readers alone;
- job: a fresh Python process running the rule's script (``workflow/scripts/
  descriptors.py``: imports, stage, store), as Snakemake's benchmark file would time it,
  less Snakemake's own script preamble.

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

from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_workflow import REPO, cycled_config, data_folder, run_snakemake  # noqa: E402

from vprflow.core import stores  # noqa: E402
from vprflow.planning.config import validate_config  # noqa: E402
from vprflow.planning.plan import build_plan  # noqa: E402
from vprflow.stages.runner import run_stage  # noqa: E402


def prepare(data: Path, workdir: Path, n_images: int, methods: list[str] | None = None):
    """The corridor config on the cycled set (``methods`` of it, default all), its plan,
    and the descriptors stages, their inputs built by Snakemake in ``workdir``."""
    config, config_path = cycled_config(data, workdir, n_images, methods)
    config = validate_config(config, REPO / "workflow" / "schemas" / "config.schema.yaml")
    plan = build_plan(config)
    targets = sorted(
        {p for s in plan.stages["descriptors"].values() for p in s.input_paths().values()}
    )
    missing = [t for t in targets if not (workdir / t).exists()]
    if missing:
        run_snakemake([
            sys.executable, "-m", "snakemake", "--snakefile", str(REPO / "workflow" / "Snakefile"),
            "--directory", str(workdir), "--configfile", str(config_path), "--cores", "2",
            *missing,
        ])  # fmt: skip
    return plan


def best_of(function, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return min(times)


def method_name(stage) -> str:
    params = stage.record["params"]
    name = params["aggregator"]
    if name == "segvlad":
        name += f" order {params['order']}" + (" + pca" if "pca" in stage.inputs else "")
    return name


# The rule's own script, run in a fresh process with the ``snakemake`` object it reads,
# so that the job timed is the job the workflow runs.
JOB = """
import json, runpy, sys
from types import SimpleNamespace
script, inputs, params, out, n, threads = json.loads(sys.argv[1])
class Inputs(dict):
    __getattr__ = dict.__getitem__
snakemake = SimpleNamespace(
    input=Inputs(inputs), params=Inputs(record=params), output=[out], log=["/dev/null"],
    wildcards=Inputs(start="0", stop=str(n)), threads=threads,
)
runpy.run_path(script, init_globals={"snakemake": snakemake})
"""


def measure(stage, workdir: Path, repeats: int, threads: int) -> tuple[float, ...]:
    """(stage, arithmetic, read, job) seconds per image of one descriptors stage."""
    from vprflow.core.registry import aggregator
    from vprflow.stages.dataset import Dataset
    from vprflow.stages.features import FeatureReader
    from vprflow.stages.jobs import Job, run_job
    from vprflow.stages.pca import read_pca
    from vprflow.stages.segments import MaskReader

    inputs = {name: str(workdir / path) for name, path in stage.input_paths().items()}
    n = Dataset(inputs["images"]).n_images
    out = Path(tempfile.mkdtemp(dir=workdir)) / "descriptors.zarr"
    stage_s = best_of(
        lambda: run_job(Job(stage.record, inputs, str(out), threads=threads)), repeats
    )

    # The same per-image arithmetic on every image's inputs read beforehand.
    params = stage.record["params"]
    describe = aggregator(params["aggregator"]).descriptor_function(params, inputs)
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
    script = str(REPO / "workflow" / "scripts" / "stage.py")
    job = json.dumps([script, inputs, stage.record, str(out), n, threads])
    job_s = best_of(lambda: subprocess.run([sys.executable, "-c", JOB, job], check=True), repeats)
    shutil.rmtree(out.parent)
    return stage_s / n, arithmetic_s / n, read_s / n, job_s / n


def run(
    args: argparse.Namespace, data: Path, workdir: Path, config_methods: list[str] | None = None
) -> None:
    plan = prepare(data, workdir, args.images, config_methods)
    stages = sorted(plan.stages["descriptors"].values(), key=method_name)
    rows = []

    def run_all():
        for stage in stages:
            name = method_name(stage)
            if not args.methods or name in args.methods:
                rows.append((name, *measure(stage, workdir, args.repeats, args.threads)))

    run_stage(os.devnull, run_all, args.threads)
    print(f"{args.images} corridor images, {args.threads} threads, best of {args.repeats}")
    header = (
        f"{'method':<24} {'arith ms':>9} {'stage ms':>9} {'ratio':>6} {'read ms':>8} "
        f"{'job ms':>8} {'job ratio':>9}"
    )
    print(header)
    print("-" * len(header))
    for name, stage_s, arithmetic_s, read_s, job_s in rows:
        print(
            f"{name:<24} {arithmetic_s * 1e3:>9.2f} {stage_s * 1e3:>9.2f} "
            f"{stage_s / arithmetic_s:>6.2f} {read_s * 1e3:>8.2f} {job_s * 1e3:>8.2f} "
            f"{job_s / arithmetic_s:>9.2f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, help="folder holding corridor/ ($VPRFLOW_DATA)")
    parser.add_argument("--images", type=int, default=256)
    parser.add_argument("--threads", type=int, default=2, help="the rule's thread budget")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/vprflow-bench-descriptors"))
    parser.add_argument("--methods", nargs="*", help="only these (e.g. 'segvlad order 3 + pca')")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="8 images, one repeat, anyloc_vlad and segvlad, a temporary workdir",
    )
    args = parser.parse_args()
    data = data_folder(parser, args)
    if not args.smoke:
        workdir = args.workdir.resolve() / str(args.images)
        workdir.mkdir(parents=True, exist_ok=True)
        run(args, data, workdir)
        return
    # A global and a per-segment method: the stage's two kinds of output.
    args.images, args.repeats = 8, 1
    with tempfile.TemporaryDirectory(prefix="vprflow-bench-smoke-") as workdir:
        run(args, data, Path(workdir), ["anyloc_vlad", "segvlad"])


if __name__ == "__main__":
    main()
