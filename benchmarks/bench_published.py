"""The published SegVLAD DAG (DINOv2 ViT-G/14 layer 31 value + SAM ViT-H automatic masks,
random weights at the published sizes) on corridor resized to 640 x 480, each stage
beside its arithmetic floor on the device.

    python benchmarks/bench_published.py --data ../shared/data [--device auto]
        [--dtype float32|bfloat16] [--images N] [--size published|tiny]
        [--weights DIR] [--workdir DIR] [--cores 16] [--timeout S]
    python benchmarks/bench_published.py --smoke    # tiny models, 4 images, segvlad, CPU
    python benchmarks/bench_published.py --wheels [--image-freeze FILE]

What runs: random-weight checkpoints saved like the hub's (``--size published``: DINOv2
ViT-G/14, 1,136 M parameters, and SAM ViT-H, 641 M, the architectures
bench_backbones.py and bench_sam.py time; ``tiny``: the same layer count and SAM input
side at widths of 32, for a CPU), built on the device once into ``--weights`` and reused.
Then the whole Snakemake DAG to ``results/recall_<dataset>.csv`` on the shipped config's
corridor entry with resolution 640 x 480, methods anyloc_vlad and segvlad each re-ranked by
mnn_dinov2, both models in ``--dtype``, and SAM's quality filters off (random weights
pass none, so every candidate mask reaches the NMS: the worst case). ``--images N``
cycles corridor's images to N (half references, half queries; bench_workflow.py's set);
without it, corridor as is (111 + 111). Snakemake runs with ``--scheduler greedy`` (no
pulp) and ``--resources gpu=1``: one model stage on the device at a time, so each
stage's time and memory are its own.

Columns, per stage (all its jobs): ``wall s`` (the sum of its jobs' seconds from
Snakemake's ``benchmark:`` files, model loading included), ``rate`` (images or queries a
second, the unit beside it), ``GPU MiB`` (the largest peak CUDA memory its jobs' logs
state: ``torch.cuda.max_memory_allocated``; ``-`` on a CPU), ``TFLOP`` (the stage's
arithmetic, below), ``floor s`` (TFLOP over the device's matmul rate in the stage's
dtype, measured in the same run on a large square product) and ``x floor`` (wall over
floor).

The arithmetic, from the shapes (matrix products and attention, counted by
``torch.utils.flop_counter`` on meta-device models, so no weights are touched):
- features: the ViT's blocks 0..layer on the image's patch grid (640 x 480 -> 45 x 34
  patches of 14, 1,530 tokens and the class token), per image;
- segments: SAM's image encoder at its 1024 x 1024 input plus the prompt decoder
  (transformers' SamModel) for points_per_side^2 point prompts, per image;
- vocabulary: k-means' assignment product, N x K x D x 2 per iteration, N =
  min(max_descriptors, references x patches), for n_iter iterations (the stage stops
  earlier where the objective stops changing);
- matches: per query, its K candidates' patch products, K x P x P x D x 2;
- descriptors, PCA, search, re-ranking's scoring, recall: small; no floor.

``--wheels`` prints the distributions that vprflow's requirements pull in and a CUDA
PyTorch image lacks, for a GPU machine without network access (benchmarks/README.md).

``--data`` defaults to ``$VPRFLOW_DATA``; with neither, ``--smoke`` exits with status 77.
"""

from __future__ import annotations

import argparse
import csv
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import NamedTuple

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_workflow import (  # noqa: E402
    REPO,
    benchmark_rows,
    data_folder,
    make_set,
    one_dataset_config,
    snakemake_command,
)

from vprflow.stages import runner  # noqa: E402

RESOLUTION = (640, 480)  # width, height
# --smoke's: corridor's own resolution (11 x 8 patches of 14), and SAM at a 64-pixel input
# (tests/tiny_models.py's, bench_sam.py's smoke model): the tiny models' cost at 640 x 480
# and SAM's 1024 side was most of the smoke's.
SMOKE_RESOLUTION, SMOKE_SAM_SIDE = (160, 120), 64
METHODS = ["anyloc_vlad", "segvlad"]
RERANKER = "mnn_dinov2"
BACKBONE, SEGMENTER = "dinov2_vitg14", "sam_vith"
# runner.CUDA_PEAK's number, where a job's resources line has it.
CUDA_PEAK = re.compile(re.sub(r"%\\\.\df", r"([\\d.]+)", re.escape(runner.CUDA_PEAK)))
# What a CUDA PyTorch image brings (the lent H200's, as the gpu-published tool found it),
# with everything these require; --image-freeze replaces it with a machine's own list.
IMAGE_HAS = ["torch", "transformers", "scikit-image", "opencv-python-headless", "h5py", "pyyaml"]
# Not needed on the GPU machine: pulp only serves Snakemake's ILP scheduler (this runs
# --scheduler greedy); vprflow itself runs from the checkout's src/.
NOT_CARRIED = {"pulp", "vprflow"}


# ---------------------------------------------------------------- checkpoints


def build_model(name: str, size: str):
    """A random-weight transformers model, seeded, on the current default device."""
    import torch
    import transformers

    tests = str(REPO / "tests")
    if tests not in sys.path:
        sys.path.insert(0, tests)
    import bench_backbones
    import bench_sam
    from tiny_models import tiny_vit

    torch.manual_seed(0)
    if name == "dinov2":
        if size == "published":
            return tiny_vit(**bench_backbones.ARCHITECTURES["dinov2-vitg14"], scale=None)
        # ViT-G's depth (so layer 31 as published) at a width of 32.
        return tiny_vit("dinov2", num_layers=40, image_size=518, scale=None)
    if size == "smoke":
        from tiny_models import tiny_sam

        return tiny_sam(model_size=SMOKE_SAM_SIDE, scale=None).eval()
    _, config_name, config = bench_sam.LARGE["sam-vit-h"]
    if size == "tiny":
        config_name, config = "SamConfig", bench_sam.MODELS["tiny"]
    return transformers.SamModel(getattr(transformers, config_name)(**config)).eval()


def checkpoints(size: str, folder: Path, device) -> dict[str, Path]:
    """``{"dinov2": path, "sam": path}``, saved in float32 under ``folder/size`` on the
    first call (built on ``device``: the published sizes take minutes on a CPU) and
    reused after."""
    import torch

    paths = {}
    for name in ("dinov2", "sam"):
        path = folder / size / name
        if not path.is_dir():
            start = time.perf_counter()
            partial = path.with_name(name + ".tmp")
            shutil.rmtree(partial, ignore_errors=True)
            with torch.device(device):
                model = build_model(name, size)
            model.save_pretrained(partial)
            count = sum(p.numel() for p in model.parameters())
            del model
            os.replace(partial, path)
            seconds = time.perf_counter() - start
            print(f"# {name}: {count / 1e6:.1f} M parameters built and saved in {seconds:.0f} s")
        paths[name] = path
    return paths


# ---------------------------------------------------------------- arithmetic


def _counted(run) -> float:
    """FLOPs of ``run()`` by torch's flop counter."""
    import torch
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter, torch.no_grad():
        run()
    return float(counter.get_total_flops())


def vit_flops(path: Path, layer: int, grid: tuple[int, int]) -> float:
    """One image through blocks 0..``layer`` of the checkpoint's ViT on an ``h x w`` grid."""
    import torch
    from transformers import AutoConfig, AutoModel

    config = AutoConfig.from_pretrained(path)
    config.num_hidden_layers = layer + 1  # vprflow.models.vit drops the blocks after it
    with torch.device("meta"):
        model = AutoModel.from_config(config).eval().requires_grad_(False)
        image = torch.empty(1, 3, grid[0] * config.patch_size, grid[1] * config.patch_size)
    return _counted(lambda: model(pixel_values=image))


def sam_flops(path: Path, prompts: int) -> tuple[float, float]:
    """(image encoder, prompt decoder for ``prompts`` point prompts) FLOPs of one image."""
    import torch
    from transformers import SamConfig, SamModel

    config = SamConfig.from_pretrained(path)
    side = config.vision_config.image_size
    with torch.device("meta"):
        model = SamModel(config).eval().requires_grad_(False)
        image = torch.empty(1, 3, side, side)
        points = torch.empty(1, prompts, 1, 2)
        labels = torch.ones(1, prompts, 1, dtype=torch.long)
        embedding = model.get_image_embeddings(image)
        encoder = _counted(lambda: model.get_image_embeddings(image))
        decoder = _counted(
            lambda: model(
                image_embeddings=embedding,
                input_points=points,
                input_labels=labels,
                multimask_output=True,
            )
        )
    return encoder, decoder


def matmul_rate(device, dtype, side: int, repeats: int = 5) -> float:
    """FLOP/s of the fastest of ``repeats`` ``side x side`` products on ``device``
    (``dtype``: a torch dtype or its name)."""
    import torch

    dtype = getattr(torch, dtype) if isinstance(dtype, str) else dtype
    a = torch.randn(side, side, device=device).to(dtype)
    b = torch.randn(side, side, device=device).to(dtype)

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    (a @ b).sum().item()  # warm-up: kernel choice, clocks
    best = float("inf")
    for _ in range(repeats):
        sync()
        start = time.perf_counter()
        for _ in range(4):
            a @ b
        sync()
        best = min(best, (time.perf_counter() - start) / 4)
    return 2 * side**3 / best


class Floor(NamedTuple):
    flops: float  # the stage's arithmetic, all its jobs
    dtype: str  # whose matmul rate bounds it


def floors(
    config: dict, weights: dict[str, Path], n_ref: int, n_query: int, resolution: tuple[int, int]
) -> dict:
    """Per stage with a floor: its :class:`Floor`, and the notes that explain it, for images
    at ``resolution`` (width, height)."""
    backbone = config["backbones"][BACKBONE]
    segmenter = config["segmenters"][SEGMENTER]
    from transformers import AutoConfig

    vit = AutoConfig.from_pretrained(weights["dinov2"])
    patch, width = vit.patch_size, vit.hidden_size
    grid = (resolution[1] // patch, resolution[0] // patch)
    patches = grid[0] * grid[1]
    images = n_ref + n_query
    per_image = vit_flops(weights["dinov2"], backbone["layer"], grid)
    encoder, decoder = sam_flops(weights["sam"], segmenter["points_per_side"] ** 2)
    vocabulary = config["vocabulary"]
    n_points = min(vocabulary["max_descriptors"], n_ref * patches)
    kmeans = n_points * vocabulary["n_clusters"] * width * 2 * vocabulary["n_iter"]
    top_k = min(config["rerankers"][RERANKER].get("top_k", 100), n_ref)
    per_query = top_k * patches * patches * width * 2
    notes = [
        f"features: {per_image / 1e12:.3f} TFLOP an image (blocks 0..{backbone['layer']}, "
        f"{grid[1]} x {grid[0]} patches of {patch}, width {width})",
        f"segments: {(encoder + decoder) / 1e12:.3f} TFLOP an image (encoder "
        f"{encoder / 1e12:.3f}, decoder {decoder / 1e12:.3f} for "
        f"{segmenter['points_per_side'] ** 2} prompts)",
        f"vocabulary: {kmeans / 1e12:.3f} TFLOP ({n_points} x {vocabulary['n_clusters']} x "
        f"{width} x 2 x {vocabulary['n_iter']} iterations at most)",
        f"matches: {per_query / 1e12:.3f} TFLOP a query ({top_k} candidates x {patches}^2 "
        f"patches x {width} x 2)",
    ]
    return {
        "features": Floor(per_image * images, backbone["dtype"]),
        "segments": Floor((encoder + decoder) * images, segmenter["dtype"]),
        "vocabulary": Floor(kmeans, "float32"),  # per job
        "matches": Floor(per_query * n_query, "float32"),  # per job (one per method)
    }, notes


# ---------------------------------------------------------------- the run


def dataset(args: argparse.Namespace, data: Path) -> tuple[dict, Path, str, int, int]:
    """The config (written under the workdir), its path, the dataset's name and its
    reference and query counts."""
    changes = {
        "resolution": list(args.resolution),
        "methods": args.methods,
        "rerank": {method: [RERANKER] for method in args.methods},
        "defaults": {"features": BACKBONE, "segmenter": SEGMENTER, "pca": args.pca},
    }
    settings = {"device": args.device}
    if args.images:
        make_set(data / "corridor", args.workdir / "data" / "cycled", args.images)
        name, root, changes["path"] = "cycled", args.workdir / "data", "cycled"
    else:
        name, root = "corridor", data
    config, path = one_dataset_config(args.workdir, root, name, changes, **settings)
    folder = root / config["datasets"][name]["path"]
    counts = [
        sum(1 for f in (folder / config["datasets"][name][role]).iterdir() if f.is_file())
        for role in ("reference", "query")
    ]
    return config, path, name, *counts


def use_models(config: dict, path: Path, weights: dict[str, Path], args) -> None:
    config["backbones"][BACKBONE].update(model=str(weights["dinov2"]), dtype=args.dtype)
    config["segmenters"][SEGMENTER].update(
        model=str(weights["sam"]),
        dtype=args.dtype,
        points_per_side=args.points_per_side,
        pred_iou_thresh=0.0,
        stability_score_thresh=0.0,
    )
    config["vocabulary"]["n_clusters"] = args.clusters
    path.write_text(yaml.safe_dump(config))


def run_dag(command: list[str], log: Path, timeout: float | None) -> tuple[int, float]:
    """Snakemake's status and wall seconds; its output to ``log``. Past ``timeout`` the
    whole process group (Snakemake and its jobs) is stopped."""
    start = time.perf_counter()
    with open(log, "w") as out:
        process = subprocess.Popen(
            command, stdout=out, stderr=subprocess.STDOUT, start_new_session=True
        )
        try:
            status = process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGTERM)
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
            status = 124
    return status, time.perf_counter() - start


def cuda_peak(logs) -> float | None:
    """The largest peak CUDA memory (MiB) the logs' resources lines state."""
    found = [float(m) for log in logs for m in CUDA_PEAK.findall(log.read_text(errors="replace"))]
    return max(found, default=None)


class Row(NamedTuple):
    label: str
    jobs: int
    seconds: float  # its jobs' wall seconds, summed
    items: int  # images or queries its jobs went through
    unit: str
    peak: float | None  # MiB of CUDA memory, where a job used CUDA
    floor: Floor | None


# The DAG's order; per stage, the items a job goes through ("all": the dataset's images,
# split among the stage's jobs) and their unit.
STAGES = {
    "images": (None, ""),
    "dataset": (None, ""),
    "features": ("all", "img"),
    "segments": ("all", "img"),
    "vocabulary": ("references", "img"),
    "descriptors": ("images", "img"),
    "pca": (None, ""),
    "search": ("queries", "query"),
    "matches": ("queries", "query"),
    "rerank": ("queries", "query"),
    "recall": (None, ""),
}


def stage_rows(workdir: Path, counts: dict[str, int], stage_floors: dict) -> list[Row]:
    """One row per stage, and one per re-ranked method for ``matches`` (found through
    the ``logs/by-method`` links), in the DAG's order."""
    jobs = benchmark_rows(workdir)
    logs = workdir / "logs"
    rows = []
    for stage in sorted(jobs, key=lambda s: list(STAGES).index(s) if s in STAGES else len(STAGES)):
        per_job, unit = STAGES.get(stage, (None, ""))
        if stage == "matches":
            links = sorted(logs.glob("by-method/*/*/matches"))
            # "<method>+<re-ranker>"
            parts = [(f"matches {link.parent.name.split('+')[0]}", link) for link in links]
        else:
            parts = [(stage, logs / stage)]
        for label, folder in parts:
            found = [
                float(next(csv.DictReader(open(path), delimiter="\t"))["s"])
                for path in folder.rglob("*.benchmark.tsv")
            ]
            seconds = sum(found) if stage == "matches" else sum(j.seconds for j in jobs[stage])
            n = len(found) if stage == "matches" else len(jobs[stage])
            items = 0 if per_job is None else counts[per_job] * (1 if per_job == "all" else n)
            floor = stage_floors.get(stage)
            if floor and stage in ("vocabulary", "matches"):  # a floor per job
                floor = Floor(floor.flops * n, floor.dtype)
            peak = cuda_peak(folder.rglob("*.log"))
            rows.append(Row(label, n, seconds, items, unit, peak, floor))
    return rows


def device_line(device) -> str:
    import torch

    name = torch.cuda.get_device_name(device) if device.type == "cuda" else device.type
    threads = f", {torch.get_num_threads()} threads" if device.type == "cpu" else ""
    return f"{name}{threads}, torch {torch.__version__}"


def commit() -> str:
    result = subprocess.run(
        ["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    )
    dirty = subprocess.run(["git", "-C", str(REPO), "diff", "--quiet", "HEAD"]).returncode
    return (result.stdout.strip() or "unknown") + ("+changes" if dirty else "")


def print_table(rows: list[Row], wall: float, rates: dict[str, float]) -> None:
    header = (
        f"{'stage':<20} {'jobs':>4} {'wall s':>8} {'rate':>8} {'unit':<7} {'GPU MiB':>8} "
        f"{'TFLOP':>8} {'floor s':>8} {'x floor':>8}"
    )
    print(header)
    print("-" * len(header))
    jobs = sum(row.jobs for row in rows)
    print(f"{'whole DAG (wall)':<20} {jobs:>4} {wall:>8.1f}")
    for row in rows:
        rate = f"{row.items / row.seconds:.2f}" if row.items and row.seconds else "-"
        peak = "-" if row.peak is None else f"{row.peak:.0f}"
        cells = f"{'-':>8} {'-':>8} {'-':>8}"
        if row.floor:
            floor_s = row.floor.flops / rates[row.floor.dtype]
            cells = f"{row.floor.flops / 1e12:>8.2f} {floor_s:>8.3f} {row.seconds / floor_s:>8.1f}"
        print(
            f"{row.label:<20} {row.jobs:>4} {row.seconds:>8.1f} {rate:>8} {row.unit:<7} "
            f"{peak:>8} {cells}"
        )


def run(args: argparse.Namespace, data: Path) -> int:
    from vprflow.core.devices import resolve_device

    device = resolve_device(args.device)
    if args.workdir.exists():
        shutil.rmtree(args.workdir)
    args.workdir.mkdir(parents=True)
    start = time.perf_counter()
    weights = checkpoints(args.size, args.weights, device)
    print(
        f"# checkpoints ready in {time.perf_counter() - start:.0f} s ({args.weights / args.size})"
    )
    config, config_path, name, n_ref, n_query = dataset(args, data)
    use_models(config, config_path, weights, args)
    target = f"results/recall_{name}.csv"
    command = snakemake_command(args.workdir, config_path, args.cores, target)
    command += ["--scheduler", "greedy", "--resources", "gpu=1"]
    log = args.workdir / "snakemake.log"
    status, wall = run_dag(command, log, args.timeout)

    # After the DAG, so that no job shares the device with it.
    rates = {
        dtype: matmul_rate(device, dtype, args.matmul_side)
        for dtype in dict.fromkeys(["float32", args.dtype])
    }
    stage_floors, notes = floors(config, weights, n_ref, n_query, args.resolution)
    counts = {
        "all": n_ref + n_query,
        "images": n_ref + n_query,
        "references": n_ref,
        "queries": n_query,
    }
    print(
        f"# {name}: {n_ref} + {n_query} images at {args.resolution[0]} x {args.resolution[1]}, "
        f"--size {args.size}, --dtype {args.dtype}, device {device_line(device)}, "
        f"commit {commit()}"
    )
    print(
        "# matmul rate on the device: "
        + ", ".join(f"{d} {r / 1e12:.2f} TFLOP/s" for d, r in rates.items())
        + f" ({args.matmul_side} x {args.matmul_side}, fastest of 5)"
    )
    for note in notes:
        print(f"# {note}")
    if status:
        print(f"# snakemake stopped with status {status} (124: --timeout): see {log}")
    print_table(stage_rows(args.workdir, counts, stage_floors), wall, rates)
    if status:
        print("\n".join(log.read_text(errors="replace").splitlines()[-30:]), file=sys.stderr)
        return 1
    return 0


# ---------------------------------------------------------------- wheels


def requirement_closure(roots) -> dict:
    """Every installed distribution ``roots`` require, transitively (extras left out),
    by canonical name: its ``Distribution``, or None where not installed."""
    from importlib.metadata import PackageNotFoundError, distribution

    from packaging.requirements import Requirement
    from packaging.utils import canonicalize_name

    found: dict = {}
    todo = list(roots)
    while todo:
        name = canonicalize_name(todo.pop())
        if name in found:
            continue
        try:
            found[name] = distribution(name)
        except PackageNotFoundError:
            found[name] = None
            continue
        for text in found[name].requires or []:
            requirement = Requirement(text)
            if requirement.marker is None or requirement.marker.evaluate({"extra": ""}):
                todo.append(requirement.name)
    return found


def wheels(image_freeze: Path | None) -> None:
    """The distributions to carry: vprflow's requirement closure here, less the image's."""
    from packaging.utils import canonicalize_name

    if image_freeze:
        lines = image_freeze.read_text().splitlines()
        names = [re.split(r"[=<>@ ;]", line.strip())[0] for line in lines]
        has = {canonicalize_name(n) for n in names if n and not n.startswith("#")}
        source = f"the distributions {image_freeze} lists"
    else:
        has = set(requirement_closure(IMAGE_HAS))
        source = f"{', '.join(IMAGE_HAS)} and what they require"
    need = requirement_closure(["vprflow"])
    carry = sorted(n for n in need if n not in has and n not in NOT_CARRIED)
    missing = [n for n in carry if need[n] is None]
    if missing:
        sys.exit(f"not installed here, so their versions are unknown: {', '.join(missing)}")
    print(f"# vprflow's requirements less {source}; pulp left out (--scheduler greedy)")
    header = f"{'distribution':<40} {'version':<14} wheel"
    print(header)
    print("-" * len(header))
    pins = []
    for name in carry:
        dist = need[name]
        wheel = dist.read_text("WHEEL") or ""
        kind = "pure" if re.search(r"^Tag: .*-none-any$", wheel, flags=re.M) else "binary"
        print(f"{dist.metadata['Name']:<40} {dist.version:<14} {kind}")
        pins.append(f"{dist.metadata['Name']}=={dist.version}")
    print(
        "\n# on a connected machine, for the GPU machine's Python (here 3.12, manylinux x86-64):\n"
        "pip download --no-deps --only-binary=:all: --python-version 3.12 "
        "--platform manylinux_2_28_x86_64 -d wheels " + " ".join(pins)
    )


# ---------------------------------------------------------------- main


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, help="folder holding corridor/ ($VPRFLOW_DATA)")
    parser.add_argument("--device", default="auto", help="the config's device (default auto)")
    parser.add_argument("--dtype", choices=["float32", "bfloat16"], default="float32")
    parser.add_argument("--images", type=int, help="corridor cycled to N (default: as is)")
    parser.add_argument("--size", choices=["published", "tiny"], default="published")
    parser.add_argument(
        "--weights", type=Path, default=Path(tempfile.gettempdir()) / "vprflow-published-weights"
    )
    parser.add_argument("--workdir", type=Path, default=Path("/tmp/vprflow-bench-published"))
    parser.add_argument("--cores", type=int, default=os.cpu_count() or 2)
    parser.add_argument("--timeout", type=float, help="seconds before the DAG is stopped")
    parser.add_argument("--points-per-side", type=int, default=32)
    parser.add_argument("--clusters", type=int, default=32)
    parser.add_argument("--matmul-side", type=int, default=8192)
    parser.add_argument("--smoke", action="store_true", help="tiny models, 4 images, segvlad, CPU")
    parser.add_argument("--wheels", action="store_true", help="print the wheels to carry")
    parser.add_argument(
        "--image-freeze", type=Path, help="with --wheels: the GPU machine's `pip freeze`"
    )
    args = parser.parse_args()
    args.pca, args.methods = {"dim": 128, "whiten": False}, METHODS
    args.resolution = RESOLUTION
    if args.wheels:
        wheels(args.image_freeze)
        return
    data = data_folder(parser, args)
    if not args.smoke:
        sys.exit(run(args, data))
    # Every stage at its smallest: 2 references, 2 queries (one reference leaves the PCA
    # too few segments), 16 prompts an image; segvlad alone, whose DAG holds anyloc_vlad's
    # stages and the segments; the tiny ViT (ViT-G's depth), SAM at a 64-pixel input,
    # corridor's resolution (SMOKE_RESOLUTION).
    args.size, args.device, args.images, args.cores = "smoke", "cpu", 4, 2
    args.methods, args.resolution = ["segvlad"], SMOKE_RESOLUTION
    args.points_per_side, args.clusters, args.matmul_side = 4, 8, 256
    args.pca = {"dim": 8, "whiten": False}
    with tempfile.TemporaryDirectory(prefix="vprflow-bench-published-smoke-") as folder:
        args.workdir, args.weights = Path(folder) / "run", Path(folder) / "weights"
        sys.exit(run(args, data))


if __name__ == "__main__":
    main()
