"""Per-image reuse (issue 52): the features and segments jobs of a map, of the same map
grown by a few images, and of the same database with a second query set.

    python benchmarks/bench_reuse.py --data ../shared/data [--images 2000] [--added 20]
    python benchmarks/bench_reuse.py --smoke     # 8 images, 2 added

Corridor's images cycled to ``--images`` (half references, half queries), each copy made
a distinct image by bytes appended after its JPEG data (decoders stop at the end marker:
the same pixels, another SHA-256), at corridor's shipped settings (DAISY features, SLIC
segments, 160 x 120; segments in each masks layout, ``vprflow.core.masks``), run in this
process through the rules' runners (``vprflow.stages.jobs.run_job``) into one results
folder:

- ``map``: the map from scratch;
- ``grown``: the map plus ``--added`` new references;
- ``second``: the map's references with ``--images / 2`` new queries;
- ``fixed``: a 2-image dataset from scratch, each stage's fixed cost.

Columns: the job's wall seconds, images computed and reused (its log line), its share of
the map's job, its chunk files that are another store's too (hard links: on disk once),
and whether the grown job is within 2% of the map's plus the fixed cost, by two
measures of it: the 2-image job in this process (its own work), and in a process of its
own, as a Snakemake job runs (Python and the job's imports too).
``lookup`` is ``vprflow.core.reuse.find_sources`` over the map's images once its store
is there (every image found: more than a first run's lookup, which finds none), and its
share of the map's job.
``--data`` defaults to ``$VPRFLOW_DATA``; with neither the script exits with status 77.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import yaml

from vprflow.core import reuse
from vprflow.planning.config import validate_config
from vprflow.planning.plan import build_plan
from vprflow.stages.jobs import Job, run_job

REPO = Path(__file__).resolve().parents[1]
SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"
SKIPPED = 77
# Each stage measured, and the segmenter's masks_layout (vprflow.core.masks) for segments.
STAGES = (("features", None), ("segments", "packed"), ("segments", "per_image"))


def distinct_copies(files: list[Path], target: Path, first: int, count: int, tag: str) -> None:
    """``count`` copies of ``files`` cycled, from number ``first``, each with its own
    bytes after the image data (``tag`` and its number)."""
    target.mkdir(parents=True, exist_ok=True)
    for i in range(first, first + count):
        source = files[i % len(files)]
        (target / f"{i:06d}{source.suffix}").write_bytes(source.read_bytes() + f"{tag}{i}".encode())


def make_data(corridor: Path, root: Path, n_images: int, added: int) -> None:
    refs = sorted((corridor / "ref").iterdir())
    queries = sorted((corridor / "query").iterdir())
    half = n_images // 2
    distinct_copies(refs, root / "map" / "ref", 0, half, "r")
    distinct_copies(queries, root / "map" / "query", 0, half, "q")
    shutil.copytree(root / "map", root / "grown")
    distinct_copies(refs, root / "grown" / "ref", half, added, "r")
    (root / "second").mkdir()
    shutil.copytree(root / "map" / "ref", root / "second" / "ref")
    distinct_copies(queries, root / "second" / "query", 0, half, "second-q")
    distinct_copies(refs, root / "fixed" / "ref", 0, 1, "fixed-r")
    distinct_copies(queries, root / "fixed" / "query", 0, 1, "fixed-q")


def plan_for(root: Path, masks_layout: str | None = None):
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    corridor = config["datasets"]["corridor"]
    if masks_layout is not None:
        for segmenter in config["segmenters"].values():
            segmenter["masks_layout"] = masks_layout
    config["data_root"] = str(root)
    config["datasets"] = {
        name: {
            **corridor,
            "path": name,
            "methods": ["segvlad"],
            "rerank": {},
            "ground_truth": {"kind": "none"},
        }
        for name in ("map", "grown", "second", "fixed")
    }
    config["targets"] = ["map"]
    return build_plan(validate_config(config, SCHEMA))


class Lines(logging.Handler):
    def __init__(self):
        super().__init__(logging.INFO)
        self.lines: list[str] = []

    def emit(self, record):
        self.lines.append(record.getMessage())


def run_stage(plan, stage: str, dataset: str, root: Path, cache: Path, lines: Lines):
    """``(wall seconds, computed, reused)`` of ``dataset``'s ``stage`` job (its images
    store built first, untimed)."""
    (images_key,) = [k for k, s in plan.stages["images"].items() if s.dataset == dataset]
    images = cache / "images" / f"{images_key}.zarr"
    if not images.exists():
        run_job(Job(plan.get("images", images_key).record, {}, str(images), data_root=str(root)))
    (key,) = [k for k, s in plan.stages[stage].items() if s.dataset == dataset]
    job = Job(
        plan.get(stage, key).record,
        {"images": str(images)},
        str(cache / stage / f"{key}.zarr"),
        data_root=str(root),
    )
    job = replace(job, run={"device": "cpu", "batch_size": 1}, threads=2)
    started = time.perf_counter()
    run_job(job)
    wall = time.perf_counter() - started
    computed, reused = re.fullmatch(reuse.IMAGES_PATTERN, lines.lines[-1]).groups()
    return wall, int(computed), int(reused), job


def run_fixed(plan, stage: str, root: Path, cache: Path, lines: Lines) -> tuple[float, float]:
    """Wall seconds of the 2-image dataset's ``stage`` job from scratch: ``(in this
    process, in its own)``. The first is the job's own work, the second what a job of a
    Snakemake run costs besides (its process: Python, the job's imports)."""
    wall, _, _, job = run_stage(plan, stage, "fixed", root, cache, lines)
    shutil.rmtree(job.out)
    started = time.perf_counter()
    subprocess.run(
        [sys.executable, "-c", CHILD, json.dumps(dataclasses.asdict(job))],
        check=True,
        capture_output=True,
    )
    alone = time.perf_counter() - started
    shutil.rmtree(job.out)
    return wall, alone


# A job in its own process, as a rule's script runs it (the runner's thread settings first).
CHILD = """
import json, sys
import vprflow.stages.runner
from vprflow.stages.jobs import Job, run_job
run_job(Job(**json.loads(sys.argv[1])))
"""


def shared_files(store: Path) -> str:
    """``shared / all`` chunk files of ``store``'s per-image array (features, masks):
    those that are also another store's (hard links)."""
    (array,) = [store / name for name in ("features", "masks") if (store / name).is_dir()]
    files = [path for path in array.rglob("*") if path.is_file() and path.name != "zarr.json"]
    return f"{sum(path.stat().st_nlink > 1 for path in files)} / {len(files)}"


def measure(data: Path, workdir: Path, n_images: int, added: int) -> bool:
    root, cache = workdir / "data", workdir / "results" / "cache"
    make_data(data / "corridor", root, n_images, added)
    lines = Lines()
    logger = logging.getLogger("vprflow")
    logger.addHandler(lines)
    logger.setLevel(logging.INFO)
    ok = True
    print("| stage | dataset | wall s | computed | reused | share of map | files shared | check |")
    print("|---|---|---|---|---|---|---|---|")
    for stage, masks_layout in STAGES:
        plan = plan_for(root, masks_layout)
        label = stage if masks_layout is None else f"{stage} ({masks_layout})"
        # The best of two: the first job of a stage in this process also imports.
        runs = [run_fixed(plan, stage, root, cache, lines) for _ in range(2)]
        in_process, alone = (min(times) for times in zip(*runs, strict=True))
        first, computed, reused, job = run_stage(plan, stage, "map", root, cache, lines)
        print(f"| {label} | map | {first:.2f} | {computed} | {reused} | 1.00 | | |")
        ok &= computed == n_images // 2 * 2 and reused == 0
        # The lookup alone, where every image is found (a second job over the map's images).
        digests = reuse.stores.read_strings(reuse.stores.open_store(job.inputs["images"]), "sha256")
        started = time.perf_counter()
        reuse.find_sources(job.inputs["images"], job.record, digests, range(len(digests)))
        lookup = time.perf_counter() - started
        for name, new in (("grown", added), ("second", n_images // 2)):
            wall, computed, reused, grown = run_stage(plan, stage, name, root, cache, lines)
            check = ""
            if name == "grown":
                check = "<= 2% + fixed: " + ", ".join(
                    f"{how} ({fixed:.2f} s) {'yes' if wall <= 0.02 * first + fixed else 'NO'}"
                    for how, fixed in (("in process", in_process), ("own process", alone))
                )
            else:
                check = f"database recomputed: {'no' if reused == n_images // 2 else 'YES'}"
                ok &= reused == n_images // 2
            ok &= computed == new
            share = wall / first
            files = shared_files(Path(grown.out))
            print(
                f"| {label} | {name} | {wall:.2f} | {computed} | {reused} | {share:.3f} "
                f"| {files} | {check} |"
            )
        share = lookup / first
        print(f"| {label} | lookup | {lookup:.4f} | | {len(digests)} | {share:.4f} | | all found |")
    logger.removeHandler(lines)
    return ok


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, help="folder holding corridor/ ($VPRFLOW_DATA)")
    parser.add_argument("--images", type=int, default=2000)
    parser.add_argument("--added", type=int, default=20)
    parser.add_argument("--workdir", type=Path, help="default: a temporary folder")
    parser.add_argument("--smoke", action="store_true", help="8 images, 2 added")
    args = parser.parse_args()
    data = args.data or (Path(os.environ["VPRFLOW_DATA"]) if "VPRFLOW_DATA" in os.environ else None)
    if data is None or not (data / "corridor").is_dir():
        print("no corridor under --data or $VPRFLOW_DATA", file=sys.stderr)
        sys.exit(SKIPPED)
    if args.smoke:
        args.images, args.added = 8, 2
    with tempfile.TemporaryDirectory(prefix="vprflow-bench-reuse-") as scratch:
        workdir = args.workdir or Path(scratch)
        ok = measure(data.resolve(), workdir, args.images, args.added)
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
