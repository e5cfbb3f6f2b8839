"""Per-image cost of the trained VPR models (docs/methods.md §11), random weights.

Each model is built at full size directly from its module (``vprflow.models.trained``:
the published architecture with PyTorch's / transformers' random initialisation, no
checkpoint file) and run on random ImageNet-normalised images at its published input
size (the registry's ``input_size``; the models that read the images at their own size,
MegaLoc and CosPlace / EigenPlaces, at 480 x 640, NetVLAD's). Each case runs in its own
child process, so its peak memory is its own: the child builds the model, runs one
warm-up batch and then, for each of ``--batch-sizes`` (ascending), ``--repeats`` timed
batches; the best time per image is kept.

Columns: ``model``, ``variant``, ``input`` (H x W), ``dim`` (descriptor length),
``B/img`` (descriptor bytes per image stored as float32: dim x 4), ``batch``,
``ms/img`` (best of repeats, per image), ``base MiB`` (process RSS after imports, before
the model), ``peak MiB`` (the process's high-water RSS, ``ru_maxrss``, after that batch
size; on a GPU ``torch.cuda.max_memory_allocated`` instead, the column then says
``GPU``). The device is CUDA when torch sees one (``--device cpu`` forces the CPU).

Usage: python benchmarks/bench_trained.py [--repeats 3] [--batch-sizes 1,4] [--cases a,b]
           [--device auto|cpu|cuda]
       python benchmarks/bench_trained.py --smoke   # NetVLAD-128 at 64 x 64, batch 1
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

# name: (model kind, variant, module:constructor, keyword arguments, input H x W)
_T = "vprflow.models.trained"
CASES = {
    "netvlad-4096": (
        "netvlad",
        "patchnetvlad-pitts30k-4096",
        f"{_T}.netvlad:NetVLADModel",
        {"num_clusters": 64, "num_pcs": 4096},
        (480, 640),
    ),
    "netvlad-32768": (
        "netvlad",
        "patchnetvlad-pitts30k-32768",
        f"{_T}.netvlad:NetVLADModel",
        {"num_clusters": 64, "num_pcs": None},
        (480, 640),
    ),
    "netvlad-512": (
        "netvlad",
        "patchnetvlad-pitts30k-512",
        f"{_T}.netvlad:NetVLADModel",
        {"num_clusters": 64, "num_pcs": 512},
        (480, 640),
    ),
    "netvlad-128": (
        "netvlad",
        "patchnetvlad-pitts30k-128",
        f"{_T}.netvlad:NetVLADModel",
        {"num_clusters": 64, "num_pcs": 128},
        (480, 640),
    ),
    "salad": ("salad", "dino_salad", f"{_T}.salad:SALAD", {}, (322, 322)),
    "boq_dinov2": ("boq_dinov2", "dinov2_12288", f"{_T}.boq_dinov2:BoQDinoV2", {}, (322, 322)),
    "megaloc": ("megaloc", "megaloc", f"{_T}.megaloc:MegaLoc", {}, (480, 640)),
    "mixvpr": ("mixvpr", "resnet50_4096", f"{_T}.mixvpr:MixVPR", {}, (320, 320)),
    "convap": ("convap", "resnet50_4096", f"{_T}.convap:ConvAP", {}, (320, 320)),
    "boq_resnet50": ("boq_resnet50", "resnet50_16384", f"{_T}.boq:BoQResNet", {}, (384, 384)),
    # EigenPlaces' ResNet50_2048 is the same network (same module, same sizes).
    "cosplace": (
        "cosplace/eigenplaces",
        "ResNet50_2048",
        f"{_T}.cosplace:GeoLocalizationNet",
        {"backbone": "ResNet50", "dim": 2048},
        (480, 640),
    ),
}
# One case takes every path of the script; NetVLAD-128 is the cheapest to build and run.
SMOKE_CASES = ["netvlad-128"]
SMOKE_SIZE = (64, 64)


def peak_mib() -> float:
    # Linux reports ru_maxrss in KiB (macOS in bytes; this script targets Linux).
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def build(name: str):
    import importlib

    import torch

    _, _, target, kwargs, _ = CASES[name]
    module, constructor = target.split(":")
    factory = getattr(importlib.import_module(module), constructor)
    torch.manual_seed(0)
    return factory(**kwargs)


def run_case(name: str, size: tuple[int, int], repeats: int, batches: list[int], device: str):
    """Child process: build ``name``, warm up, time each batch size."""
    import torch
    import transformers  # noqa: F401  (imported before the baseline RSS)

    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    gpu = device.startswith("cuda")
    base = peak_mib()
    model = build(name).eval().to(device)
    height, width = size
    generator = torch.Generator().manual_seed(0)

    def images(batch: int) -> torch.Tensor:
        return torch.randn(batch, 3, height, width, generator=generator).to(device)

    def sync() -> None:
        if gpu:
            torch.cuda.synchronize()

    rows = []
    with torch.inference_mode():
        dim = int(model(images(batches[0])).shape[1])  # warm-up
        sync()
        for batch in batches:
            x = images(batch)
            if gpu:
                torch.cuda.reset_peak_memory_stats()
            best = float("inf")
            for _ in range(repeats):
                start = time.perf_counter()
                model(x)
                sync()
                best = min(best, time.perf_counter() - start)
            peak = torch.cuda.max_memory_allocated() / 2**20 if gpu else peak_mib()
            rows.append(
                {
                    "batch": batch,
                    "dim": dim,
                    "s_per_image": best / batch,
                    "base_mib": base,
                    "peak_mib": peak,
                    "memory": "GPU" if gpu else "RSS",
                    "device": device,
                    "threads": torch.get_num_threads(),
                }
            )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="timed batches (best kept)")
    parser.add_argument("--batch-sizes", default="1,4", help="comma-separated, e.g. 1,4")
    parser.add_argument("--cases", help=f"comma-separated subset of {', '.join(CASES)}")
    parser.add_argument("--device", default="auto", help="auto (CUDA if present), cpu, cuda")
    parser.add_argument("--smoke", action="store_true", help="netvlad-128, 64 x 64, batch 1")
    parser.add_argument("--run", nargs=3, metavar=("CASE", "H", "W"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.smoke:
        args.cases, args.batch_sizes, args.repeats, args.device = (
            ",".join(SMOKE_CASES),
            "1",
            1,
            "cpu",
        )
    batches = sorted({int(b) for b in str(args.batch_sizes).split(",") if b.strip()})
    if args.run:
        name, height, width = args.run
        size = (int(height), int(width))
        print(json.dumps(run_case(name, size, args.repeats, batches, args.device)))
        return

    names = args.cases.split(",") if args.cases else list(CASES)
    unknown = [name for name in names if name not in CASES]
    if unknown:
        sys.exit(f"unknown cases {unknown}; expected some of {list(CASES)}")
    header = (
        f"{'model':<21} {'variant':<28} {'input':>8} {'dim':>6} {'B/img':>7} {'batch':>5}"
        f" {'ms/img':>9} {'base MiB':>9} {'peak MiB':>9}"
    )
    print(f"batch sizes {batches}, best of {args.repeats} after a warm-up, random weights")
    print(header)
    print("-" * len(header))
    row = None
    for name in names:
        kind, variant, _, _, size = CASES[name]
        size = SMOKE_SIZE if args.smoke else size
        command = [sys.executable, __file__, "--run", name, *map(str, size)]
        command += ["--repeats", str(args.repeats), "--batch-sizes", ",".join(map(str, batches))]
        command += ["--device", args.device]
        run = subprocess.run(command, capture_output=True, text=True)
        if run.returncode:
            sys.stderr.write(run.stderr)
            sys.exit(f"{name} failed (status {run.returncode})")
        for row in json.loads(run.stdout.strip().splitlines()[-1]):
            peak = f"{row['peak_mib']:.0f}" + (" GPU" if row["memory"] == "GPU" else "")
            print(
                f"{kind:<21} {variant:<28} {size[0]:>3}x{size[1]:<4} {row['dim']:>6}"
                f" {4 * row['dim']:>7} {row['batch']:>5} {1000 * row['s_per_image']:>9.2f}"
                f" {row['base_mib']:>9.0f} {peak:>9}",
                flush=True,
            )
    if row is not None:
        print(f"device: {row['device']}, torch threads: {row['threads']}")


if __name__ == "__main__":
    main()
