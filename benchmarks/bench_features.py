"""The features stage end to end (reading, resizing, the model, writing the store) on a
random ViT, before and after a given revision, beside its arithmetic floor.

    python benchmarks/bench_features.py                      # dinov2-vits14, CPU
    python benchmarks/bench_features.py --device cuda --cases dinov2-vitg14,dinov2-vitg14-bf16 \\
        --images 64 --batch-sizes 1,auto
    python benchmarks/bench_features.py --smoke              # tiny-dinov2, 4 images

On a machine reached without git, save the old stage first and name the copy:
``git show 023a60e:src/vprflow/stages/features.py > before_features.py``, then
``--before before_features.py``.

What runs: the architecture of ``--cases`` (benchmarks/bench_backbones.py's, random
weights) saved like a hub checkpoint; a synthetic dataset of ``--images`` images (half
references, half queries, tests/synthetic.py's places) at the case's input size; its
images stage; then the features stage's function on one job of all the images, with the
shipped config's entry for the model (``resolution: dataset``, ``resize: method``),
``--threads`` host threads, for each of ``--batch-sizes`` (``auto``: today's code only), the code
of ``--before`` (``git show REV:src/vprflow/stages/features.py`` loaded as a module;
default: the last commit whose stage read, computed and wrote in turn) and today's,
interleaved, best of ``--repeats``. The stores of every run are compared with the
first's, value for value: a difference is printed, and is an error on the CPU.

Columns: ``code`` (before / after), ``batch`` (as configured), ``load s`` (the model's
loading inside the stage), ``ms/img`` (the stage's wall time less the loading, per
image), ``floor ms`` (the forward's FLOPs an image, counted by ``torch.utils.flop_counter``
on one image through the loaded backbone, over the device's matmul rate in the model's
dtype, measured in this run on a square product), ``x floor`` (ms/img over floor ms).
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import sys
import tempfile
import time
import types
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
os.environ.setdefault("TQDM_DISABLE", "1")  # the stage's progress bar, before tqdm loads
sys.path[:0] = [str(ROOT / "src"), str(ROOT / "tests"), str(ROOT / "benchmarks")]

from bench_backbones import CASES, build  # noqa: E402
from bench_published import matmul_rate  # noqa: E402
from revisions import module_at  # noqa: E402

# The last commit whose features stage read, computed and wrote one batch after another.
BEFORE = "023a60e"
SCHEMA = ROOT / "workflow" / "schemas" / "config.schema.yaml"


def stage_module(before: str) -> types.ModuleType:
    """The features stage of ``before``: a git revision, or a file holding its source."""
    return module_at(before, "vprflow.stages.features", "before_features")


def forward_flops(backbone, height: int, width: int) -> float:
    """FLOPs of one image through the backbone's forward (matrix products, attention)."""
    from torch.nn.attention import SDPBackend, sdpa_kernel
    from torch.utils.flop_counter import FlopCounterMode

    counter = FlopCounterMode(display=False)
    # Attention as its products: the counter has no formula for the CPU's fused kernel.
    with counter, sdpa_kernel(SDPBackend.MATH):
        backbone.features(np.zeros((1, height, width, 3), np.float32))
    return float(counter.get_total_flops())


def prepare(case: str, root: Path, n_images: int):
    """The saved model, the images store and the features stage's record of ``case``."""
    from synthetic import make_dataset
    from workflow_helpers import toy_config

    from vprflow.planning.config import validate_config
    from vprflow.planning.plan import build_plan
    from vprflow.stages.base import Job
    from vprflow.stages.dataset import build_images

    architecture, (height, width), params = CASES[case]
    model = root / architecture
    if not model.exists():
        build(architecture).save_pretrained(model)
    data = root / f"data-{height}x{width}"
    if not data.exists():
        make_dataset(data / "toy", n_places=n_images // 2, width=width, height=height)
    params = {k: v for k, v in params.items() if k != "attention"}
    config = toy_config(data, resolution=[width, height], methods=["gem"])
    config["datasets"]["toy"]["defaults"] = {"features": "bench"}
    config["backbones"]["bench"] = {**params, "model": str(model)}
    plan = build_plan(validate_config(config, SCHEMA))
    images = plan.get("images", plan.images_keys["toy"])
    dataset = root / f"dataset-{height}x{width}.zarr"
    if not dataset.exists():
        build_images(Job(images.record, {}, str(dataset), data_root=str(data)))
    features = next(iter(plan.stages["features"].values()))
    return features.record, str(dataset), str(data), params


def run_stage(module, record, dataset, data_root, out, device, batch, threads):
    """Seconds of the stage, and of the model's loading within it."""
    from vprflow.stages.base import Job

    loaded = {}
    load_model = module.load_model

    def timed(*args, **kwargs):
        start = time.perf_counter()
        model = load_model(*args, **kwargs)
        loaded["s"] = time.perf_counter() - start
        return model

    module.load_model = timed
    try:
        job = Job(
            record,
            {"images": dataset},
            out,
            data_root=data_root,
            run={"device": device, "batch_size": batch},
            threads=threads,
        )
        start = time.perf_counter()
        module.compute_features(job)
        return time.perf_counter() - start, loaded["s"]
    finally:
        module.load_model = load_model


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="dinov2-vits14", help=f"of {', '.join(CASES)}")
    parser.add_argument("--images", type=int, default=16, help="images (even)")
    parser.add_argument("--batch-sizes", default="1,auto", help="comma-separated, auto included")
    parser.add_argument("--device", default="cpu", help="auto, cpu, cuda, cuda:N")
    parser.add_argument("--threads", type=int, default=2, help="torch and host threads")
    parser.add_argument("--repeats", type=int, default=2, help="runs of each (best kept)")
    parser.add_argument("--before", default=BEFORE, help="old stage: git revision or file")
    parser.add_argument(
        "--smoke", action="store_true", help="tiny-dinov2, 4 images, once, a 256-side matmul"
    )
    args = parser.parse_args()
    if args.smoke:
        args.cases, args.images, args.repeats = "tiny-dinov2", 4, 1

    import torch

    from vprflow.core import stores
    from vprflow.core.devices import resolve_device, resolve_dtype
    from vprflow.models.loaders import load_model
    from vprflow.stages import features as after

    torch.set_num_threads(args.threads)
    chosen = []  # what batch_size auto chose, from the stage's log
    handler = logging.Handler()
    handler.emit = lambda record: chosen.append(record.getMessage())
    logging.getLogger("vprflow").addHandler(handler)
    logging.getLogger("vprflow").setLevel(logging.INFO)
    device = resolve_device(args.device)
    codes = {"before": stage_module(args.before), "after": after}
    batches = [b if b == "auto" else int(b) for b in args.batch_sizes.split(",")]
    differences: set[str] = set()
    header = (
        f"{'case':<20} {'dtype':<9} {'code':<6} {'batch':>5} {'images':>6} {'load s':>7}"
        f" {'ms/img':>9} {'floor ms':>9} {'x floor':>8}"
    )
    print(f"{device}, {args.threads} threads, best of {args.repeats}, before = {args.before}")
    print(header)
    print("-" * len(header))
    with tempfile.TemporaryDirectory() as folder:
        root = Path(folder)
        for case in args.cases.split(","):
            record, dataset, data_root, params = prepare(case, root, args.images)
            dtype = params.get("dtype", "float32")
            backbone = load_model("features", {**record["params"]}, str(device))
            height, width = CASES[case][1]
            flops = forward_flops(backbone, height, width)
            del backbone
            side = 256 if args.smoke else 4096 if device.type == "cuda" else 1024
            rate = matmul_rate(device, resolve_dtype(dtype, device), side)
            floor_ms = 1000 * flops / rate
            best: dict[tuple, tuple] = {}
            reference = None
            for repeat in range(args.repeats):
                for batch in batches:
                    for code, module in codes.items():
                        if code == "before" and batch == "auto":
                            continue  # before: whole numbers only
                        out = str(root / f"{case}-{code}-{batch}-{repeat}.zarr")
                        seconds, load = run_stage(
                            module, record, dataset, data_root, out, str(device), batch,
                            args.threads,
                        )  # fmt: skip
                        stored = np.asarray(stores.open_store(out)["features"][...])
                        shutil.rmtree(out)
                        if reference is None:
                            reference = stored
                        elif not np.array_equal(stored, reference):
                            differ = stored != reference
                            gap = float(np.abs(stored - reference).max())
                            differences.add(
                                f"{case} {code} batch {batch}: {int(differ.sum())} of "
                                f"{differ.size} values differ from the first run's, by up "
                                f"to {gap:.3g}"
                            )
                        key = (code, batch)
                        if key not in best or seconds - load < best[key][0] - best[key][1]:
                            best[key] = (seconds, load)
            for (code, batch), (seconds, load) in best.items():
                ms = 1000 * (seconds - load) / args.images
                print(
                    f"{case:<20} {dtype:<9} {code:<6} {batch!s:>5} {args.images:>6}"
                    f" {load:>7.2f} {ms:>9.1f} {floor_ms:>9.2f} {ms / floor_ms:>8.1f}",
                    flush=True,
                )
            for line in sorted({m for m in chosen if m.startswith("batch_size auto")}):
                print(f"{case}: {line}")
            chosen.clear()
    print(f"matmul rate {rate / 1e9:.0f} GFLOP/s ({dtype}, side {side})")
    for line in sorted(differences):
        print(line)
    if differences and device.type == "cpu":
        sys.exit("features differ on the CPU")  # the CPU path promises identical features
    if not differences:
        print("features identical in every run")


if __name__ == "__main__":
    main()
