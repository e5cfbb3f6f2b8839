"""Per-image time and peak memory of ``vprflow.models.vit`` backbones (random weights).

Each case runs in its own child process so that its peak RSS (``ru_maxrss``) is its
own: the child builds the architecture with random weights, saves it to a temporary
directory, loads it through ``load_vit`` (the production path), runs one warm-up batch
of the first batch size and then, for each of ``--batch-sizes`` (ascending), ``--repeats``
timed batches; the best time per image is reported.

Columns: ``attn`` (the attention kernel: ``sdpa``, which transformers picks by default
for DINOv2 / DINOv3 / DINO, or ``eager`` for the ``*-eager`` cases), ``batch``, ``load s``
(load_vit incl. reading weights), ``ms/img`` (best of repeats), ``img/s``, ``base MiB``
(RSS after imports, before the model), ``peak MiB`` (process high-water mark after that
batch size; batch sizes run in ascending order in one process, so it is the peak of the
largest batch so far), ``grid`` (h x w x D of the output).

Usage: python benchmarks/bench_backbones.py [--repeats N] [--batch-sizes 1,2,4,8]
           [--giant] [--cases name,name]
       python benchmarks/bench_backbones.py --smoke    # tiny-dinov2, batch 1, one repeat
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CASES = {
    # name: (architecture, image H x W, load_vit params)
    "tiny-dinov2": (
        "tiny-dinov2",
        (480, 640),
        {"backbone": "dinov2", "layer": 1, "facet": "value"},
    ),
    "tiny-dino": (
        "tiny-dino",
        (224, 224),
        {"backbone": "dino", "facet": "token", "final_norm": True},
    ),
    "dinov2-vits14": (
        "dinov2-vits14",
        (480, 640),
        {"backbone": "dinov2", "layer": 11, "facet": "value"},
    ),
    "dinov2-vits14-bf16": (
        "dinov2-vits14",
        (480, 640),
        {"backbone": "dinov2", "layer": 11, "facet": "value", "dtype": "bfloat16"},
    ),
    "dino-vitb8": (
        "dino-vitb8",
        (224, 224),
        {"backbone": "dino", "facet": "token", "final_norm": True},
    ),
    "dino-vitb8-bf16": (
        "dino-vitb8",
        (224, 224),
        {"backbone": "dino", "facet": "token", "final_norm": True, "dtype": "bfloat16"},
    ),
    # DINOv3 ViT-L/16 at the registry's default block (18 of 24), 30 x 40 patches.
    "dinov3-vitl16": (
        "dinov3-vitl16",
        (480, 640),
        {"backbone": "dinov3", "layer": 18, "facet": "value"},
    ),
    "dinov3-vitl16-bf16": (
        "dinov3-vitl16",
        (480, 640),
        {"backbone": "dinov3", "layer": 18, "facet": "value", "dtype": "bfloat16"},
    ),
    "dinov3-vitl16-eager": (
        "dinov3-vitl16",
        (480, 640),
        {"backbone": "dinov3", "layer": 18, "facet": "value", "attention": "eager"},
    ),
    # Opt-in (--giant): the AnyLoc / SegVLAD backbone, ~4.4 GiB of float32 weights.
    "dinov2-vitg14": (
        "dinov2-vitg14",
        (480, 640),
        {"backbone": "dinov2", "layer": 31, "facet": "value"},
    ),
    "dinov2-vitg14-bf16": (
        "dinov2-vitg14",
        (480, 640),
        {"backbone": "dinov2", "layer": 31, "facet": "value", "dtype": "bfloat16"},
    ),
    "dinov2-vitg14-eager": (
        "dinov2-vitg14",
        (480, 640),
        {"backbone": "dinov2", "layer": 31, "facet": "value", "attention": "eager"},
    ),
}
GIANT_CASES = ["dinov2-vitg14", "dinov2-vitg14-bf16", "dinov2-vitg14-eager"]
DEFAULT_CASES = [
    name for name in CASES if name not in GIANT_CASES and name != "dinov3-vitl16-eager"
]


# name: keyword arguments of ``tiny_vit`` in tests/tiny_models.py (which makes real-size
# architectures too); weights keep the transformers initialisation, seeded with 0.
ARCHITECTURES = {
    "tiny-dinov2": {"kind": "dinov2", "image_size": 56},
    "tiny-dino": {"kind": "dino"},
    "dinov2-vits14": {
        "kind": "dinov2",
        "hidden_size": 384,
        "num_layers": 12,
        "num_heads": 6,
        "mlp_ratio": 4,
        "image_size": 518,
    },
    "dinov2-vitg14": {
        "kind": "dinov2",
        "hidden_size": 1536,
        "num_layers": 40,
        "num_heads": 24,
        "mlp_ratio": 4,
        "image_size": 518,
        "use_swiglu_ffn": True,
    },
    # facebook/dinov3-vitl16-pretrain-lvd1689m's architecture (4 registers, RoPE).
    "dinov3-vitl16": {
        "kind": "dinov3",
        "hidden_size": 1024,
        "num_layers": 24,
        "num_heads": 16,
        "mlp_ratio": 4,
        "registers": 4,
        "image_size": 224,
    },
    "dino-vitb8": {
        "kind": "dino",
        "hidden_size": 768,
        "num_layers": 12,
        "num_heads": 12,
        "mlp_ratio": 4,
    },
}


def build(architecture: str):
    """A randomly initialised transformers model of the named architecture."""
    if architecture not in ARCHITECTURES:
        raise ValueError(f"unknown architecture {architecture!r}")
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
    from tiny_models import tiny_vit

    return tiny_vit(**ARCHITECTURES[architecture], seed=0, scale=None)


def peak_mib() -> float:
    # Linux reports ru_maxrss in KiB (macOS in bytes; this script targets Linux).
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def save_case(architecture: str, directory: str) -> None:
    """Child process: build random weights and save them (kept out of the measured child)."""
    build(architecture).save_pretrained(directory)


def run_case(
    name: str, directory: str, repeats: int, batches: list[int], warm_up: bool = True
) -> list[dict]:
    """Child process: load through ``load_vit`` and time ``features`` per batch size
    (after one warm-up batch, unless ``warm_up`` is false)."""
    import numpy as np
    import torch
    import transformers  # noqa: F401  (imported before measuring the baseline RSS)

    from vprflow.models.vit import load_vit

    _, (height, width), params = CASES[name]
    params = dict(params)
    attention = params.pop("attention", None)
    generator = np.random.default_rng(0)
    base = peak_mib()
    start = time.perf_counter()
    backbone = load_vit({**params, "model": directory}, "cpu")
    load = time.perf_counter() - start
    if attention is not None:
        backbone.model.set_attn_implementation(attention)
    if warm_up:
        images = generator.random((batches[0], height, width, 3), dtype=np.float32)
        backbone.features(images)
    rows = []
    for batch in batches:
        images = generator.random((batch, height, width, 3), dtype=np.float32)
        best = float("inf")
        for _ in range(repeats):
            start = time.perf_counter()
            features = backbone.features(images)
            best = min(best, time.perf_counter() - start)
        rows.append(
            {
                "name": name,
                "dtype": params.get("dtype", "float32"),
                "attention": backbone.model.config._attn_implementation,
                "batch": batch,
                "input": f"{height}x{width}",
                "grid": "x".join(map(str, features.shape[1:])),
                "layer": backbone.layer,
                "facet": backbone.facet,
                "load_s": load,
                "ms_per_image": 1000 * best / batch,
                "images_per_s": batch / best,
                "base_mib": base,
                "peak_mib": peak_mib(),
                "threads": torch.get_num_threads(),
            }
        )
    return rows


def child(args: list[str]) -> subprocess.CompletedProcess:
    run = subprocess.run([sys.executable, __file__, *args], capture_output=True, text=True)
    if run.returncode:
        # The child's traceback: CalledProcessError would only say that it failed.
        sys.stderr.write(run.stderr)
        sys.exit(f"{' '.join(args[:2])} failed (status {run.returncode})")
    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="timed batches (best kept)")
    parser.add_argument(
        "--batch-sizes",
        "--batch",
        default="1",
        help="comma-separated images per batch, e.g. 1,2,4,8 (timed in ascending order)",
    )
    parser.add_argument(
        "--giant", action="store_true", help="also DINOv2 ViT-G/14, sdpa and eager (slow)"
    )
    parser.add_argument("--cases", help=f"comma-separated subset of {', '.join(CASES)}")
    parser.add_argument("--save", nargs=2, metavar=("ARCH", "DIR"), help=argparse.SUPPRESS)
    parser.add_argument("--run", nargs=2, metavar=("CASE", "DIR"), help=argparse.SUPPRESS)
    parser.add_argument(
        "--smoke", action="store_true", help="tiny-dinov2 only, batch 1, one repeat"
    )
    args = parser.parse_args()
    if args.smoke:
        # A process that imports transformers costs seconds: the smoke's one child builds
        # and saves the weights itself (their memory then counts in its peak) and times
        # its one batch without a warm-up.
        args.cases, args.batch_sizes, args.repeats = "tiny-dinov2", "1", 1

    if args.save:
        save_case(*args.save)
        return
    batches = sorted({int(b) for b in str(args.batch_sizes).split(",") if b.strip()})
    if args.run:
        if args.smoke:
            save_case(CASES[args.run[0]][0], args.run[1])
        rows = run_case(args.run[0], args.run[1], args.repeats, batches, not args.smoke)
        print(json.dumps(rows))
        return

    names = args.cases.split(",") if args.cases else list(DEFAULT_CASES)
    if args.giant:
        names += [name for name in GIANT_CASES if name not in names]
    header = (
        f"{'case':<20} {'dtype':<9} {'attn':<6} {'batch':>5} {'input':>8} {'grid hxwxD':>12}"
        f" {'layer':>5} {'facet':>6} {'load s':>7} {'ms/img':>9} {'img/s':>7}"
        f" {'base MiB':>9} {'peak MiB':>9}"
    )
    print(f"batch sizes {batches}, best of {args.repeats}, CPU, random weights")
    print(header)
    print("-" * len(header))
    with tempfile.TemporaryDirectory() as root:
        saved: dict[str, str] = {}
        for name in names:
            architecture = CASES[name][0]
            if architecture not in saved:
                saved[architecture] = f"{root}/{architecture}"
                if not args.smoke:
                    child(["--save", architecture, saved[architecture]])
            run = child(
                ["--run", name, saved[architecture], "--repeats", str(args.repeats),
                 "--batch-sizes", ",".join(map(str, batches)), *["--smoke"] * args.smoke]
            )  # fmt: skip
            for row in json.loads(run.stdout.strip().splitlines()[-1]):
                print(
                    f"{row['name']:<20} {row['dtype']:<9} {row['attention']:<6}"
                    f" {row['batch']:>5} {row['input']:>8} {row['grid']:>12}"
                    f" {row['layer']:>5} {row['facet']:>6} {row['load_s']:>7.2f}"
                    f" {row['ms_per_image']:>9.1f} {row['images_per_s']:>7.3f}"
                    f" {row['base_mib']:>9.0f} {row['peak_mib']:>9.0f}",
                    flush=True,
                )
        print(f"torch threads: {row['threads']}")


if __name__ == "__main__":
    main()
