"""The whole workflow at a papers' dataset size: a Pittsburgh-30k-shaped synthetic city
(10,000 references to 6,816 queries), per stage time, share, peak memory and store size,
and how each grows with the number of images.

    python benchmarks/bench_city.py --data ../shared/data [--images 2000 8000 16816]
        [--cores 2] [--workdir /tmp/vprflow-city] [--cache /tmp/vprflow-city-data] [--reuse]
    python benchmarks/bench_city.py --smoke     # 16 images, segvlad + mnn only, temporary folders

The images (weight-free, generated once per N and kept under ``--cache``): N_ref =
round(N * 10,000 / 16,816) references, the rest queries, laid out and named as the
``pitts30k`` preset reads them (``images/test/database``, ``images/test/queries``,
``@<utm_east>@<utm_north>@...@.jpg``), so its ``utm`` ground truth (25 m) applies. Places
lie on a serpentine lattice of streets ``PLACE_SPACING`` metres apart; each place shows
one crop of a shared image (corridor, and roadscene's visible and thermal images when
present), randomly placed, flipped and tinted; its ``VIEWS`` references are small
re-crops of it within ``REF_JITTER`` metres, and each query a larger re-crop of a random
place's view within ``QUERY_OFFSET`` metres. So every query's positives are exactly its
place's references and every other reference is more than 25 m away. Gaussian noise
makes every file's bytes distinct (checked). Images are written at the corridor entry's
resolution (160 x 120).

The run: the shipped ``config/config.yaml`` with its corridor entry's methods,
re-rankers, resolution and defaults, the preset's layout and ground truth, and the
shipped shard settings, through Snakemake to the recall table. Per stage: jobs; seconds
(the jobs' ``benchmark:`` files; stages without one, from Snakemake's log, 1 s
resolution); share of all job-seconds; peak memory (largest max RSS of a job, MiB);
bytes of the stage's stores on disk (``results/cache/<stage>``). Between sizes, the
growth exponent of time and of store bytes (slope of log against log N). Then SegVLAD's
segment-descriptor store beside Revisit-Anything's 6.65 GB for Pittsburgh 30k.

``--data`` defaults to ``$VPRFLOW_DATA``; with neither, ``--smoke`` exits with status 77.

``--make-smoke-run FOLDER`` makes the one run that the smoke modes of bench_city.py,
bench_workflow.py, bench_fixed_cost.py and bench_descriptors.py share (smoke_run.py:
this script's 16-image smoke city, on one core); with ``$VPRFLOW_SMOKE_RUN`` naming that
folder (tests/repository/test_benchmarks.py sets it), ``--smoke`` reads it instead of
making a run of its own.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import itertools
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ProcessPoolExecutor
from datetime import datetime
from pathlib import Path

import numpy as np
import yaml
from PIL import Image

sys.path.insert(0, str(Path(__file__).parent))
from bench_fixed_cost import CORES, recorded_run  # noqa: E402
from bench_workflow import (  # noqa: E402
    REPO,
    SMOKE_METHODS,
    SMOKE_RERANK,
    benchmark_rows,
    data_folder,
    one_dataset_config,
    run_snakemake,
    snakemake_command,
)
from smoke_run import RECORD, TARGET, shared_run  # noqa: E402

from vprflow.data.presets import presets  # noqa: E402

# Pittsburgh 30k's test split (the pitts30k preset): 10,000 references, 6,816 queries.
PITTS_REFERENCES, PITTS_IMAGES = 10_000, 16_816
# Revisit-Anything's reported size of SegVLAD's segment descriptors for Pittsburgh 30k,
# and the published descriptor: PCA to 1024 dimensions, float32.
PAPER_BYTES, PAPER_DIM, PAPER_ITEMSIZE = 6.65e9, 1024, 4
# The route (metres): places on a lattice PLACE_SPACING apart, so two places' images are
# at least PLACE_SPACING - REF_JITTER - QUERY_OFFSET = 27 m apart, beyond the 25 m rule,
# while a query is within REF_JITTER + QUERY_OFFSET = 13 m of its place's references.
PLACE_SPACING, REF_JITTER, QUERY_OFFSET = 40.0, 3.0, 10.0
VIEWS = 4  # references per place
# Pittsburgh's UTM zone 17T and a point in it: the names look like the preset's.
ORIGIN, ZONE = (584_000.0, 4_477_000.0), (17, "T")
# Bump when the generator changes what it writes: a cached set of another version is redone.
GENERATOR_VERSION = 1
SMOKE_IMAGES = 16


def route(n_images: int, seed: int = 0) -> tuple[list[dict], list[dict]]:
    """Every reference and query: its place, source-crop parameters and UTM position.

    Pure function of ``(n_images, seed)``; the sources are indexed modulo their count
    at render time."""
    rng = np.random.default_rng(seed)
    n_ref = round(n_images * PITTS_REFERENCES / PITTS_IMAGES)
    n_query = n_images - n_ref
    n_places = math.ceil(n_ref / VIEWS)
    width = math.ceil(math.sqrt(n_places))
    places = []
    for p in range(n_places):
        row, col = divmod(p, width)
        col = col if row % 2 == 0 else width - 1 - col  # serpentine: one continuous route
        places.append(
            {
                "xy": (ORIGIN[0] + PLACE_SPACING * col, ORIGIN[1] + PLACE_SPACING * row),
                "source": int(rng.integers(1 << 30)),  # taken modulo the sources' count
                "scale": float(rng.uniform(0.6, 0.85)),  # of the source's largest 4:3 box
                "centre": rng.uniform(0, 1, 2).tolist(),  # where the box sits, in its slack
                "flip": bool(rng.integers(2)),
                "tint": rng.uniform(0.75, 1.25, 3).tolist(),  # per channel
            }
        )

    def view(place: int, shift: float, radius: float, index: int, role: str) -> dict:
        angle, r = rng.uniform(0, 2 * np.pi), radius * math.sqrt(rng.uniform())
        x, y = places[place]["xy"]
        return {
            "place": place,
            "role": role,
            "index": index,
            "xy": (x + r * math.cos(angle), y + r * math.sin(angle)),
            "shift": rng.uniform(-shift, shift, 2).tolist(),  # of the place's box
            "zoom": float(rng.uniform(0.9, 1.0)),
            "gain": float(rng.uniform(0.92, 1.08)),
            "noise_seed": int(rng.integers(1 << 62)),
        }

    references = [view(i // VIEWS, 0.08, REF_JITTER, i, "ref") for i in range(n_ref)]
    queries = [
        view(int(rng.integers(n_places)), 0.15, QUERY_OFFSET, i, "query") for i in range(n_query)
    ]
    return places, references + queries


def utm_name(image: dict) -> str:
    """The image's file name, VPR-datasets-downloader's ``@``-separated fields: UTM
    east, north, zone number and letter, lat, lon (left empty), pano id, tile, ...; the
    ``utm`` ground truth reads the first two."""
    east, north = image["xy"]
    utm = f"@{east:010.2f}@{north:010.2f}@{ZONE[0]:02d}@{ZONE[1]}@@"
    return f"{utm}@city{image['role']}{image['index']:06d}@{image['place']:06d}@@@@@@@.jpg"


_SOURCES: list[Image.Image] = []  # a worker's decoded sources


def _load_sources(paths: list[str]) -> None:
    _SOURCES[:] = [Image.open(p).convert("RGB") for p in paths]


def _render(job: tuple[dict, dict, tuple[int, int], str]) -> None:
    """Write one image: the place's box of its source, moved and zoomed by the view,
    resized to ``size``, flipped, tinted, gained and noised."""
    place, image, size, path = job
    source = _SOURCES[place["source"] % len(_SOURCES)]
    width, height = source.size
    aspect = size[0] / size[1]
    box_w = min(width, height * aspect) * place["scale"] * image["zoom"]
    box_h = box_w / aspect
    left = (width - box_w) * place["centre"][0] + image["shift"][0] * box_w
    top = (height - box_h) * place["centre"][1] + image["shift"][1] * box_h
    left, top = min(max(left, 0.0), width - box_w), min(max(top, 0.0), height - box_h)
    crop = source.resize(size, Image.BILINEAR, box=(left, top, left + box_w, top + box_h))
    pixels = np.asarray(crop, dtype=np.float32)
    if place["flip"]:
        pixels = pixels[:, ::-1]
    noise = np.random.default_rng(image["noise_seed"]).normal(0.0, 2.0, pixels.shape)
    pixels = pixels * np.asarray(place["tint"]) * image["gain"] + noise
    Image.fromarray(pixels.clip(0, 255).round().astype(np.uint8)).save(path, quality=90)


def sources(data: Path) -> list[Path]:
    """The shared images the city is cut from: corridor's, and roadscene's if present."""
    folders = [data / "corridor" / "ref", data / "corridor" / "query"]
    folders += [data / "roadscene" / "vi", data / "roadscene" / "ir"]
    return [p for f in folders if f.is_dir() for p in sorted(f.iterdir()) if p.is_file()]


def make_city(
    data: Path, cache: Path, n_images: int, size: tuple[int, int], workers: int = 2
) -> Path:
    """``cache/city<N>`` in the pitts30k preset's layout, made once per N and generator
    settings (``generator.json``); built under a temporary name, then renamed."""
    layout = presets()["pitts30k"].dataset
    target = cache / f"city{n_images}"
    source_paths = sources(data)
    settings = {
        "version": GENERATOR_VERSION,
        "images": n_images,
        "size": list(size),
        "sources": [str(p) for p in source_paths],
    }
    record = target / "generator.json"
    if record.is_file() and json.loads(record.read_text()) == settings:
        return target
    partial = cache / f"city{n_images}.tmp"
    shutil.rmtree(partial, ignore_errors=True)
    shutil.rmtree(target, ignore_errors=True)
    places, images = route(n_images)
    jobs = []
    for image in images:
        folder = partial / layout["reference" if image["role"] == "ref" else "query"]
        folder.mkdir(parents=True, exist_ok=True)
        jobs.append((places[image["place"]], image, size, str(folder / utm_name(image))))
    paths = [str(p) for p in source_paths]
    with ProcessPoolExecutor(workers, initializer=_load_sources, initargs=(paths,)) as pool:
        list(pool.map(_render, jobs, chunksize=64))
    seen: dict[str, str] = {}
    for _, _, _, path in jobs:
        digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()
        if digest in seen:
            sys.exit(f"generator wrote the same bytes twice: {seen[digest]} and {path}")
        seen[digest] = path
    (partial / "generator.json").write_text(json.dumps(settings))
    os.replace(partial, target)
    return target


def city_config(
    workdir: Path, city: Path, methods: list[str] | None, rerank: dict | None = None
) -> Path:
    """The shipped config over ``city``: corridor's entry (or its ``methods`` and
    ``rerank``) with the pitts30k preset's layout and ground truth (the preset's, not
    restated), shipped shard settings."""
    preset = presets()["pitts30k"].dataset
    changes = {key: preset[key] for key in ("reference", "query", "ground_truth", "denominator")}
    changes |= {"path": city.name, "source": "synthetic: benchmarks/bench_city.py"}
    if methods:
        changes |= {"methods": methods}
    if rerank:
        changes |= {"rerank": rerank}
    _, config_path = one_dataset_config(workdir, city.parent, "city", changes)
    config = yaml.safe_load(config_path.read_text())
    del config["datasets"]["city"]["download"]  # corridor's archive, not this set's
    config_path.write_text(yaml.safe_dump(config))
    return config_path


_STAMP = re.compile(r"^\[(\w{3} \w{3} +\d+ \d\d:\d\d:\d\d \d{4})\]$")
_RULE = re.compile(r"^(?:local)?rule (\w+):$")
_JOBID = re.compile(r"^\s+jobid: (\d+)$")
_FINISHED = re.compile(r"^Finished jobid: (\d+) \(Rule: (\w+)\)$")


def log_jobs(workdir: Path) -> tuple[dict[str, list[float]], dict[str, int], float]:
    """From the work folder's Snakemake logs (a run stopped and resumed has several): per
    rule, each finished job's seconds (start and finish stamps, 1 s resolution: the time
    of rules without a ``benchmark:`` file); per rule, the jobs of the whole run (those
    finished under earlier logs plus those the newest planned, its "Job stats"); and the
    seconds from first to last stamp of each log, summed."""
    jobs: dict[str, list[float]] = {}
    earlier: dict[str, int] = {}
    newest: dict[str, int] = {}
    wall = 0.0
    logs = sorted((workdir / ".snakemake" / "log").glob("*.snakemake.log"))
    for number, log in enumerate(logs):
        stamp, rule, started, stamps, finished = None, None, {}, [], {}
        lines = log.read_text().splitlines()
        for line in lines:
            if m := _STAMP.match(line):
                stamp = datetime.strptime(m.group(1), "%a %b %d %H:%M:%S %Y")
                stamps.append(stamp)
            elif m := _RULE.match(line):
                rule = m.group(1)
            elif (m := _JOBID.match(line)) and rule:
                started[m.group(1)], rule = stamp, None
            elif m := _FINISHED.match(line):
                seconds = (stamp - started.pop(m.group(1))).total_seconds()
                finished.setdefault(m.group(2), []).append(seconds)
        wall += (stamps[-1] - stamps[0]).total_seconds() if stamps else 0.0
        for name, times in finished.items():
            jobs.setdefault(name, []).extend(times)
        if number < len(logs) - 1:
            for name, times in finished.items():
                earlier[name] = earlier.get(name, 0) + len(times)
            continue
        stats = lines.index("Job stats:")
        for line in lines[stats + 3 :]:
            name, count = line.split()
            if name == "total":
                break
            newest[name] = int(count)
    planned = {name: earlier.get(name, 0) + newest.get(name, 0) for name in earlier | newest}
    return jobs, planned, wall


def store_bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def segment_store(workdir: Path, method: str) -> dict | None:
    """The descriptors store of ``method`` (from ``results/cache/index.tsv``): bytes,
    images, segments, dimension."""
    import zarr

    with open(workdir / "results" / "cache" / "index.tsv") as f:
        for row in csv.DictReader(f, delimiter="\t"):
            store = workdir / row["store"]
            if (
                row["stage"] == "descriptors"
                and method in row["methods"].split(",")
                and (store / "zarr.json").is_file()
            ):
                group = zarr.open_group(workdir / row["store"], mode="r")
                rows, dim = group["descriptors"].shape
                return {
                    "bytes": store_bytes(workdir / row["store"]),
                    "images": group["descriptors_offsets"].shape[0] - 1,
                    "segments": rows,
                    "dim": dim,
                    "itemsize": group["descriptors"].dtype.itemsize,
                }
    return None  # not yet written: a run stopped before its descriptors


class LoadSampler:
    """The 1-minute load average every 15 s while a run lasts: the machine is shared."""

    def __init__(self) -> None:
        self.samples = [os.getloadavg()[0]]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)

    def _sample(self) -> None:
        while not self._stop.wait(15):
            self.samples.append(os.getloadavg()[0])

    def __enter__(self) -> LoadSampler:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


def run_size(args: argparse.Namespace, data: Path, n_images: int) -> dict:
    """Generate, run and measure one size; the summary is also ``summary.json``.

    With ``--stop-after``, Snakemake (its process group) is stopped after that many
    seconds and the summary counts the jobs that finished, marked partial."""
    workdir = args.workdir / f"n{n_images}"
    summary_path = workdir / "summary.json"
    if args.reuse and summary_path.is_file():
        return json.loads(summary_path.read_text())
    if args.summarise:
        # What only the run itself saw (generation time, load) is kept from a summary.
        old = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
        return summarise(workdir, n_images, args.cores, old.get("generate_s"), old.get("load"))
    shutil.rmtree(workdir, ignore_errors=True)
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    size = tuple(config["datasets"]["corridor"]["resolution"])
    start = time.perf_counter()
    city = make_city(data, args.cache, n_images, size)
    generate = time.perf_counter() - start
    config_path = city_config(workdir, city, args.methods, args.rerank)
    command = snakemake_command(workdir, config_path, args.cores, "results/recall_city.csv")
    with LoadSampler() as load:
        if args.stop_after:
            run_until(command, args.stop_after, workdir / "snakemake.out")
        else:
            run_snakemake(command)
    return summarise(workdir, n_images, args.cores, generate, load.samples)


def load_summary(load: list[float] | dict | None) -> dict | None:
    """Mean and max of load samples (a summary's already summarised load as it is)."""
    if not load or isinstance(load, dict):
        return load or None
    return {"mean": float(np.mean(load)), "max": float(max(load))}


def run_until(command: list[str], seconds: float, output: Path) -> None:
    """Run Snakemake in its own process group; stop the group after ``seconds``."""
    with open(output, "w") as out:
        process = subprocess.Popen(command, stdout=out, stderr=out, start_new_session=True)
        try:
            status = process.wait(timeout=seconds)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGTERM)
            process.wait()
            return
    if status:
        print(output.read_text()[-4000:], file=sys.stderr)
        sys.exit(f"snakemake failed (status {status}); its output: {output}")


def summarise(
    workdir: Path,
    n_images: int,
    cores: int,
    generate: float | None = None,
    load: list[float] | dict | None = None,
) -> dict:
    """The summary of a run in ``workdir`` from its logs, benchmark files and stores; a
    run without its recall table (stopped early) counts its finished jobs, as partial."""
    measured = benchmark_rows(workdir)
    finished, planned, wall = log_jobs(workdir)
    stages = {}
    for rule, count in planned.items():
        seconds, rows = finished.get(rule, []), measured.get(rule)
        stages[rule] = {
            "jobs": len(seconds),
            "planned": count,
            "seconds": sum(job.seconds for job in rows) if rows else sum(seconds),
            "cpu_s": sum(job.cpu for job in rows) if rows else None,
            "peak_mib": max(job.max_rss for job in rows) if rows else None,
            "timed_by": "benchmark" if rows else "log",
            # Jobs whose CPU and peak memory come from their logs (the rest: Snakemake's
            # samples every 30 s, which miss up to a job's last 30 s).
            "exact_jobs": sum(job.exact for job in rows) if rows else 0,
        }
    cache = workdir / "results" / "cache"
    for stage, entry in stages.items():
        entry["store_bytes"] = store_bytes(cache / stage) if (cache / stage).is_dir() else None
    table = workdir / "results" / "recall_city.csv"
    recall = {}
    if table.is_file():
        with open(table) as f:
            recall = {row["method"]: float(row["recall@1"]) for row in csv.DictReader(f)}
    summary = {
        "images": n_images,
        "references": round(n_images * PITTS_REFERENCES / PITTS_IMAGES),
        "partial": not table.is_file(),
        "generate_s": generate,
        "wall_s": wall,
        "cores": cores,
        "load": load_summary(load),
        "stages": stages,
        "segvlad": segment_store(workdir, "segvlad"),
        "recall@1": recall,
    }
    path = workdir / "summary.json"
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(summary, indent=1))
    os.replace(tmp, path)
    return summary


def print_size(s: dict) -> None:
    """One size's table. Shares are of all jobs' wall seconds and of all CPU seconds
    (stages timed from the log have no CPU time): under other load, CPU is the steadier."""
    total = sum(e["seconds"] for e in s["stages"].values())
    cpu_total = sum(e.get("cpu_s") or 0.0 for e in s["stages"].values())
    made = f", images generated in {s['generate_s']:.0f} s" if s["generate_s"] else ""
    load = s["load"]
    load = f", load average mean {load['mean']:.1f} max {load['max']:.1f}" if load else ""
    partial = " PARTIAL (stopped early: finished jobs only)" if s["partial"] else ""
    print(
        f"\n{s['images']} images ({s['references']} references), {s['cores']} cores: "
        f"{s['wall_s']:.0f} s wall, {total:.0f} job-seconds, {cpu_total:.0f} CPU seconds"
        f"{made}{load}{partial}"
    )
    header = (
        f"{'stage':<12} {'jobs':>7} {'seconds':>9} {'share':>7} {'CPU s':>8} {'CPU share':>9} "
        f"{'peak MiB':>9} {'store MB':>9}"
    )
    print(header)
    print("-" * len(header))
    for stage, e in sorted(s["stages"].items(), key=lambda item: -item[1]["seconds"]):
        jobs = f"{e['jobs']}" if e["jobs"] == e["planned"] else f"{e['jobs']}/{e['planned']}"
        cpu = e.get("cpu_s")
        cpu_cells = f"{cpu:>8.1f} {100 * cpu / cpu_total:>8.1f}%" if cpu else f"{'-':>8} {'-':>9}"
        peak = f"{e['peak_mib']:.0f}" if e["peak_mib"] is not None else "-"
        store = f"{e['store_bytes'] / 1e6:.2f}" if e["store_bytes"] is not None else "-"
        share = 100 * e["seconds"] / total
        print(
            f"{stage:<12} {jobs:>7} {e['seconds']:>9.1f} {share:>6.1f}% {cpu_cells} "
            f"{peak:>9} {store:>9}"
        )
    timed = [e for e in s["stages"].values() if e["timed_by"] == "benchmark"]
    exact = sum(e.get("exact_jobs", 0) for e in timed)
    print(
        f"CPU s and peak MiB of {exact} of {sum(e['jobs'] for e in timed)} timed jobs from "
        "their logs (exact); the rest from Snakemake's samples every 30 s"
    )
    if s["recall@1"]:
        print("recall@1: " + ", ".join(f"{m} {r:.3f}" for m, r in s["recall@1"].items()))


def exponent(a: float | None, b: float | None, n_a: int, n_b: int) -> str:
    if not a or not b:
        return "-"
    return f"{math.log(b / a) / math.log(n_b / n_a):.2f}"


def print_growth(summaries: list[dict]) -> None:
    """Growth exponents of wall time, CPU time and store bytes between consecutive sizes."""
    pairs = list(itertools.pairwise(summaries))
    print("\ngrowth exponent (slope of log value against log images; - : not measured)")
    header = f"{'stage':<12} " + " ".join(
        f"{what + ' ' + str(a['images']) + '->' + str(b['images']):>20}"
        for a, b in pairs
        for what in ("time", "CPU", "store")
    )
    print(header)
    print("-" * len(header))
    stages = sorted({stage for s in summaries for stage in s["stages"]})
    for stage in stages:
        cells = []
        for a, b in pairs:
            # A stage a stopped run did not finish has no size to grow from.
            ea, eb = (
                e if e.get("jobs") == e.get("planned") else {}
                for e in (a["stages"].get(stage, {}), b["stages"].get(stage, {}))
            )
            for field in ("seconds", "cpu_s", "store_bytes"):
                value = exponent(ea.get(field), eb.get(field), a["images"], b["images"])
                cells.append(f"{value:>20}")
        print(f"{stage:<12} " + " ".join(cells))


def print_segments(summaries: list[dict]) -> None:
    """SegVLAD's segment descriptors beside Revisit-Anything's 6.65 GB for Pitts30k."""
    per_paper_image = PAPER_BYTES / (PAPER_DIM * PAPER_ITEMSIZE * PITTS_IMAGES)
    print(
        f"\nsegvlad descriptors store; Revisit-Anything: {PAPER_BYTES / 1e9:.2f} GB for "
        f"Pitts30k, i.e. {per_paper_image:.0f} segments per image at {PAPER_DIM}-d float32 "
        f"over {PITTS_IMAGES} images (implied, not stated)"
    )
    header = (
        f"{'images':>7} {'segments':>9} {'per image':>9} {'dim':>5} {'store MB':>9} "
        f"{'B/segment':>9} {'at 1024-d, 16816 images GB':>27}"
    )
    print(header)
    print("-" * len(header))
    for s in summaries:
        g = s["segvlad"]
        if g is None:
            continue
        scaled = g["bytes"] / g["images"] * PITTS_IMAGES * PAPER_DIM / g["dim"]
        print(
            f"{g['images']:>7} {g['segments']:>9} {g['segments'] / g['images']:>9.1f} "
            f"{g['dim']:>5} {g['bytes'] / 1e6:>9.1f} {g['bytes'] / g['segments']:>9.0f} "
            f"{scaled / 1e9:>27.2f}"
        )


def make_smoke_run(data: Path, root: Path) -> None:
    """The smoke run the benchmarks share (smoke_run.py) in ``root``: the smoke city's
    images in ``root/data``, the run in ``root/run``, ``root/run.json`` written last."""
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    size = tuple(config["datasets"]["corridor"]["resolution"])
    start = time.perf_counter()
    city = make_city(data, root / "data", SMOKE_IMAGES, size)
    generate = time.perf_counter() - start
    folder = root / "run"
    shutil.rmtree(folder, ignore_errors=True)
    config_path = city_config(folder, city, SMOKE_METHODS, SMOKE_RERANK)
    start = time.perf_counter()
    recorded_run(folder, config_path, TARGET)
    shards = f"shard {config['shard_size']}, descriptors {config['descriptors_shard_size']}"
    run = {"images": SMOKE_IMAGES, "cores": CORES, "shards": shards}
    run |= {"generate_s": generate, "wall": time.perf_counter() - start}
    partial = root / f"{RECORD}.tmp"
    partial.write_text(json.dumps(run))
    os.replace(partial, root / RECORD)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, help="folder holding corridor/ ($VPRFLOW_DATA)")
    parser.add_argument("--images", type=int, nargs="+", default=[2000, 8000, PITTS_IMAGES])
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/vprflow-city"))
    parser.add_argument("--cache", type=Path, default=Path("/tmp/vprflow-city-data"))
    parser.add_argument("--methods", nargs="+", help="of the config (default: corridor's)")
    parser.add_argument("--reuse", action="store_true", help="reuse a size's summary.json")
    parser.add_argument(
        "--stop-after", type=float, help="stop each size's Snakemake after SECONDS (partial)"
    )
    parser.add_argument(
        "--summarise", action="store_true", help="summarise existing work folders, run nothing"
    )
    parser.add_argument(
        "--smoke", action="store_true", help=f"{SMOKE_IMAGES} images, segvlad + mnn only, temporary"
    )
    parser.add_argument(
        "--make-smoke-run", type=Path, metavar="FOLDER", help="the smoke run others share"
    )
    parser.set_defaults(rerank=None)  # corridor's
    args = parser.parse_args()
    data = data_folder(parser, args)
    if args.make_smoke_run:
        make_smoke_run(data, args.make_smoke_run)
        return
    if args.smoke:
        args.images, args.methods, args.rerank = [SMOKE_IMAGES], SMOKE_METHODS, SMOKE_RERANK
        shared = shared_run()
        if shared:  # this script's smoke city, run once for the benchmarks (smoke_run.py)
            workdir, run = shared
            summaries = [summarise(workdir, run["images"], run["cores"], run["generate_s"])]
            print_size(summaries[0])
            print_segments(summaries)
            return
        with tempfile.TemporaryDirectory(prefix="vprflow-city-smoke-") as folder:
            args.workdir, args.cache = Path(folder) / "work", Path(folder) / "data"
            summaries = [run_size(args, data, SMOKE_IMAGES)]
            print_size(summaries[0])
            print_segments(summaries)
        return
    summaries = []
    for n in sorted(args.images):
        summaries.append(run_size(args, data, n))
        print_size(summaries[-1])
        sys.stdout.flush()
    if len(summaries) > 1:
        print_growth(summaries)
    print_segments(summaries)


if __name__ == "__main__":
    main()
