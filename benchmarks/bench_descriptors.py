"""Per-image time of the descriptors stage against the arithmetic it does, per method,
beside the stage as it was before its reads were overlapped; and each stage job's
start-up.

    python benchmarks/bench_descriptors.py --data ../shared/data [--images 256]
        [--threads 2] [--repeats 3] [--workdir /tmp/vprflow-bench-descriptors]
        [--before 2cc3dee]
    python benchmarks/bench_descriptors.py --smoke   # 4 images, anyloc_vlad and segvlad

``--data`` defaults to ``$VPRFLOW_DATA`` (a smoke run without either is skipped, status
77, as in bench_workflow.py).

Builds the descriptors stage's inputs (dataset, DAISY features, SLIC segments,
vocabulary, PCA) for a synthetic N-image set (the corridor images cycled, as
bench_workflow.py) with Snakemake, once per work directory. Then, per method of the
corridor config, in one process and under the rule's thread budget (``run_stage``):

- stage: the descriptors stage's job (``vprflow.stages.jobs.run_job``) over all images
  (store reads, PCA, writes, zarr), each run into a new store (removed untimed);
- before: the same job through ``src/vprflow/stages/descriptors.py``,
  ``src/vprflow/core/stores.py`` and the ``FeatureReader`` of
  ``src/vprflow/stages/features.py`` of ``--before`` (``git show``; default: the last
  commit whose stores wrote one chunk a zarr write), the two runs
  interleaved in every repeat so that both see the same machine load;
- zstd: the stage's job reading its features with the codecs they had before commit
  dd52bef (zstd and crc32c; since then the checksum alone, which every other column
  reads), interleaved with the other two; each from a copy of the store where the work
  folder's has the other codecs;
- arithmetic: the method's per-image ``compute`` (and PCA transform) on every image's
  inputs read beforehand (float32 features, unpacked masks), one image at a time, with
  one BLAS thread or the rule's threads, whichever is faster;
- read: reading every image's inputs through the stage's readers alone;
- job: a fresh Python process running the rule's script (``workflow/scripts/
  stage.py``: imports, stage, store), as Snakemake's benchmark file would time it,
  less Snakemake's own script preamble.

Each is the best of ``--repeats`` runs, in ms per image; "ratio" = stage / arithmetic,
"job ratio" = job / arithmetic.

Start-up (second table): per stage of ``plan.STAGES``, a fresh Python process that
imports what the stage's job imports before it runs (the rule's script's modules and
the stage's runner module): its wall time, the imports' share of it, and whether torch
or faiss came with them; the first row is ``python -c pass``, the floor (a smoke: the
descriptors stage's row alone).

With ``$VPRFLOW_SMOKE_RUN`` set (tests/repository/test_benchmarks.py sets it), ``--smoke`` reads the
one run that the smoke modes of bench_city.py, bench_workflow.py, bench_fixed_cost.py
and bench_descriptors.py share (smoke_run.py: bench_city.py's 16-image smoke city, on
one core) instead of making one of its own.
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
import types
from pathlib import Path

import numpy as np
import yaml
from threadpoolctl import threadpool_limits

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_fixed_cost import fastest, stage_module  # noqa: E402
from bench_workflow import REPO, cycled_config, data_folder, run_snakemake  # noqa: E402
from revisions import module_at  # noqa: E402
from smoke_run import shared_run  # noqa: E402

from vprflow.core import stores  # noqa: E402
from vprflow.planning.config import validate_config  # noqa: E402
from vprflow.planning.plan import STAGES, build_plan  # noqa: E402
from vprflow.stages.runner import run_stage  # noqa: E402

# The commit this benchmark's comparison starts from: before the
# stores wrote several chunks a zarr write (RowWriter, then store_rows).
BEFORE = "2cc3dee"


def load_before(rev: str) -> types.ModuleType:
    """``src/vprflow/stages/descriptors.py`` at ``rev`` as a module of its own, its
    ``stores`` being ``src/vprflow/core/stores.py`` at ``rev`` (atomic stores, the row
    reader, RowWriter) and its ``FeatureReader`` that of ``src/vprflow/stages/
    features.py`` at ``rev``; the rest of the package is imported as it is now, but for
    the modules that have moved since (served from ``rev``: :data:`MOVED_SINCE`)."""
    stores_before = module_at(rev, "vprflow.core.stores", "stores_before")
    module = module_at(rev, "vprflow.stages.descriptors", "descriptors_before", MOVED_SINCE)
    module.stores = stores_before
    # Its FeatureReader reads through the stores of rev too (the globals of features.py
    # at rev, which it was loaded with).
    module.FeatureReader.__init__.__globals__["stores"] = stores_before
    module.aggregator = _with_functions_of(module)
    return module


# The modules the descriptors stage of BEFORE imports that have moved or gone since, in
# the order they import each other.
MOVED_SINCE = (
    "vprflow.core.registry",
    "vprflow.stages.dataset",
    "vprflow.stages.features",
    "vprflow.stages.segments",
    "vprflow.stages.pca",
    "vprflow.stages.vocabulary",
)


# Each aggregator's per-image function in stages/descriptors.py as it was at BEFORE
# (each then had one of its own, ``(options, input paths) -> ImageDescriptor``).
_FUNCTIONS_BEFORE = {
    "segvlad": "segvlad_descriptors",
    "segment_gem": "segment_gem_descriptors",
    "anyloc_vlad": "anyloc_vlad_descriptor",
    "snsm": "snsm_descriptor",
    **dict.fromkeys(("gem", "average", "max"), "pooled_descriptor"),
    "model": "model_descriptor",
}


def _with_functions_of(module: types.ModuleType):
    """``aggregator`` whose entries run ``module``'s per-image functions (the readers as
    they were then), not the entries' ``compute`` as the stage runs it now."""
    from vprflow.aggregation.aggregators import aggregator

    class Entry:
        def __init__(self, name: str):
            self.entry = aggregator(name)

        def __getattr__(self, name: str):
            return getattr(self.entry, name)

        def descriptor_function(self, options: dict, inputs: dict):
            return getattr(module, _FUNCTIONS_BEFORE[self.entry.name])(options, inputs)

    return Entry


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


def shared_plan(workdir: Path, methods: list[str]):
    """The plan of the finished smoke run the benchmarks share (smoke_run.py) with
    ``methods`` as its one dataset's: their descriptors stages' inputs are in that run
    (checked: nothing is run in a folder that others read)."""
    config = yaml.safe_load((workdir / "config.yaml").read_text())
    (dataset,) = config["datasets"].values()
    dataset["methods"] = methods
    plan = build_plan(validate_config(config, REPO / "workflow" / "schemas" / "config.schema.yaml"))
    targets = {p for s in plan.stages["descriptors"].values() for p in s.input_paths().values()}
    missing = sorted(t for t in targets if not (workdir / t).exists())
    if missing:
        sys.exit(f"the shared smoke run in {workdir} lacks {', '.join(missing)}")
    return plan


def best_of(function, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return min(times)


def interleaved(calls: dict, repeats: int) -> dict:
    """``{name: fastest seconds}``, the calls taking turns in every repeat; a call
    returns the seconds it timed (its untimed cleanup outside them)."""
    best = dict.fromkeys(calls, float("inf"))
    for _ in range(repeats):
        for name, call in calls.items():
            best[name] = min(best[name], call())
    return best


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


def measure(
    stage, workdir: Path, repeats: int, threads: int, before: types.ModuleType
) -> tuple[float, ...]:
    """(stage, before, stage on zstd features, arithmetic, read, job) seconds per image of
    one descriptors stage."""
    from vprflow.aggregation.aggregators import aggregator
    from vprflow.stages.image_descriptors import image_descriptor
    from vprflow.stages.jobs import Job, run_job
    from vprflow.stages.readers import Dataset, FeatureReader, MaskReader, read_pca

    inputs = {name: str(workdir / path) for name, path in stage.input_paths().items()}
    features = inputs["features"]
    inputs["features"] = features_with(features, workdir, stores.CHECKSUM_ONLY, "crc32c")
    n = Dataset(inputs["images"]).n_images
    scratch = Path(tempfile.mkdtemp(dir=workdir))
    out = scratch / "descriptors.zarr"

    def timed(run, inputs=inputs) -> float:
        """One job into a new store: ``out`` exists from the second run on, and a job
        finding its own store there discards its copy (``replace_store``), a cost no
        workflow job has."""
        shutil.rmtree(out, ignore_errors=True)
        start = time.perf_counter()
        run(Job(stage.record, inputs, str(out), threads=threads))
        return time.perf_counter() - start

    zstd_inputs = {
        **inputs,
        "features": features_with(features, workdir, stores.COMPRESSORS, "zstd"),
    }
    best = interleaved(
        {
            "stage": lambda: timed(run_job),
            "before": lambda: timed(before.compute_descriptors),
            "zstd": lambda: timed(run_job, zstd_inputs),
        },
        repeats,
    )
    stage_s, before_s, zstd_s = best["stage"], best["before"], best["zstd"]

    # The same per-image arithmetic on every image's inputs read beforehand.
    params = stage.record["params"]
    describe = image_descriptor(aggregator(params["aggregator"]), params, inputs)
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

    def fresh_job() -> float:
        shutil.rmtree(out, ignore_errors=True)
        start = time.perf_counter()
        subprocess.run([sys.executable, "-c", JOB, job], check=True)
        return time.perf_counter() - start

    job_s = min(fresh_job() for _ in range(repeats))
    shutil.rmtree(scratch)
    return stage_s / n, before_s / n, zstd_s / n, arithmetic_s / n, read_s / n, job_s / n


def features_with(path: str, workdir: Path, codecs: tuple, label: str) -> str:
    """The features store at ``path`` if its array has ``codecs``, else a copy of it with
    them (same values and attributes) under ``workdir/features-<label>``: a work folder
    made before commit dd52bef holds zstd features, since then the checksum alone."""
    source = stores.open_store(path)
    array = source["features"]
    if tuple(array.raw.compressors) == tuple(codecs):
        return path
    copy = workdir / f"features-{label}" / Path(path).name
    if not copy.exists():
        with stores.atomic_store(copy, dict(source.attrs)) as group:
            group.create_array(
                "features", data=np.asarray(array), chunks=array.chunks, compressors=codecs
            )
    return str(copy)


# A stage job's imports, as the rule's script makes them, timed in a fresh process.
STARTUP = """
import sys, time
start = time.perf_counter()
import vprflow.stages.jobs, vprflow.stages.runner, {module}
imports = time.perf_counter() - start
print(imports, "torch" in sys.modules, "faiss" in sys.modules)
"""


def startup(repeats: int, stages=STAGES) -> list[tuple]:
    """``(stage, process s, imports s, torch, faiss)`` per stage of ``stages``, each the
    fastest of ``repeats`` fresh processes; first ``python -c pass``."""

    rows = [("(python -c pass)", fastest("pass", repeats)[0], 0.0, False, False)]
    for name in stages:
        seconds, out = fastest(STARTUP.format(module=stage_module(name)), repeats)
        imports, torch, faiss = out.split()
        rows.append((name, seconds, float(imports), torch == "True", faiss == "True"))
    return rows


def run(args: argparse.Namespace, plan, workdir: Path, images: str = "corridor images") -> None:
    stages = sorted(plan.stages["descriptors"].values(), key=method_name)
    before = load_before(args.before)
    rows = []

    def run_all():
        for stage in stages:
            name = method_name(stage)
            if not args.methods or name in args.methods:
                rows.append((name, *measure(stage, workdir, args.repeats, args.threads, before)))

    run_stage(os.devnull, run_all, args.threads)
    load = os.getloadavg()[0]
    print(
        f"{args.images} {images}, {args.threads} threads, best of {args.repeats}, "
        f"before = {args.before}, load average {load:.1f}"
    )
    header = (
        f"{'method':<24} {'arith ms':>9} {'stage ms':>9} {'ratio':>6} {'before ms':>10} "
        f"{'ratio':>6} {'zstd ms':>8} {'ratio':>6} {'read ms':>8} {'job ms':>8} "
        f"{'job ratio':>9}"
    )
    print(header)
    print("-" * len(header))
    for name, stage_s, before_s, zstd_s, arithmetic_s, read_s, job_s in rows:
        print(
            f"{name:<24} {arithmetic_s * 1e3:>9.2f} {stage_s * 1e3:>9.2f} "
            f"{stage_s / arithmetic_s:>6.2f} {before_s * 1e3:>10.2f} "
            f"{before_s / arithmetic_s:>6.2f} {zstd_s * 1e3:>8.2f} "
            f"{zstd_s / arithmetic_s:>6.2f} {read_s * 1e3:>8.2f} {job_s * 1e3:>8.2f} "
            f"{job_s / arithmetic_s:>9.2f}"
        )
    print()
    print(f"Start-up of a stage's job: fresh processes, fastest of {args.repeats}")
    header = f"{'stage':<18} {'process ms':>10} {'imports ms':>10} {'torch':>6} {'faiss':>6}"
    print(header)
    print("-" * len(header))
    # A smoke times the descriptors stage's alone: a process a stage, ~0.4 s of CPU each.
    stages = ["descriptors"] if args.smoke else STAGES
    for name, seconds, imports, torch, faiss in startup(args.repeats, stages):
        print(
            f"{name:<18} {seconds * 1e3:>10.0f} {imports * 1e3:>10.0f} "
            f"{'yes' if torch else 'no':>6} {'yes' if faiss else 'no':>6}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, help="folder holding corridor/ ($VPRFLOW_DATA)")
    parser.add_argument("--images", type=int, default=256)
    parser.add_argument("--threads", type=int, default=2, help="the rule's thread budget")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/vprflow-bench-descriptors"))
    parser.add_argument("--methods", nargs="*", help="only these (e.g. 'segvlad order 3 + pca')")
    parser.add_argument("--before", default=BEFORE, help="git revision of the stage compared")
    parser.add_argument(
        "--smoke",
        action="store_true",
        help="4 images, one repeat, anyloc_vlad and segvlad, a temporary workdir",
    )
    args = parser.parse_args()
    data = data_folder(parser, args)
    if not args.smoke:
        workdir = args.workdir.resolve() / str(args.images)
        workdir.mkdir(parents=True, exist_ok=True)
        run(args, prepare(data, workdir, args.images), workdir)
        return
    # A global and a per-segment method: the stage's two kinds of output. Their inputs
    # are all in the smoke run the benchmarks share (smoke_run.py), where there is one.
    args.images, args.repeats, methods = 4, 1, ["anyloc_vlad", "segvlad"]
    shared = shared_run()
    if shared:
        workdir, record = shared
        args.images = record["images"]
        run(args, shared_plan(workdir, methods), workdir, "smoke-city images (smoke_run.py)")
        return
    with tempfile.TemporaryDirectory(prefix="vprflow-bench-smoke-") as folder:
        workdir = Path(folder)
        run(args, prepare(data, workdir, args.images, methods), workdir)


if __name__ == "__main__":
    main()
