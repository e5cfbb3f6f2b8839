"""Time and memory of Segment Anything automatic mask generation per image.

Random-weight models only (no pretrained weights here), architectures from configs: a
tiny SAM; SAM with the real ViT-B architecture; and the published sizes the registry
defaults name, SAM ViT-H (``sam-vit-h``), SAM-HQ ViT-H (``sam-hq-vit-h``) and SAM 2.1
Hiera-L (``sam2-large``). ``tiny`` and ``vit-b`` are saved and read back through the
loader; the large ones are built in memory (saving 2.5 GB of random weights would
dominate), with the loader's sdpa attention and the same adapters. Each configuration
runs in a fresh subprocess so its peak RSS is its own (``--smoke``: every row of both
tables in one subprocess, so its RSS columns are not each row's own). Two filter
settings: the library thresholds (with random weights almost no candidate survives them,
so NMS is trivial) and all filters off (every candidate reaches the box NMS: the
post-processing worst case).

    python benchmarks/bench_sam.py [--device cpu] [--repeats 2] [--sides 16 32]
    python benchmarks/bench_sam.py --models sam-vit-h sam-hq-vit-h sam2-large \
        --points-per-side 32 --dtypes float32 bfloat16 --filters library

    python benchmarks/bench_sam.py --models sam-vit-h --dtypes bfloat16 --filters library \
        --points-per-side 32 --repeats 0 --image-batches 1 2 4 8
    python benchmarks/bench_sam.py --device cuda --models sam-vit-h --points-per-side 32 \
        --dtypes float32 bfloat16 --filters library none --image-batches 1 4 8
    python benchmarks/bench_sam.py --decoders [--prompts 256] [--points-per-batch 64]
    python benchmarks/bench_sam.py --smoke   # both tables at their smallest (tiny-64), CPU

``--image-batches`` adds, per configuration, the image encoder's time per image on
batches of B images (``SamSegmenter.generate_batch`` embeds a batch in one pass, then
decodes prompts image by image, on an accelerator all of an image's points in one pass
when its free memory allows): a whole image then costs encoder(B)/B plus the decoding
time measured on the single image, with the process's peak memory after that batch.

``--decoders`` times prompt decoding alone, at the published decoder sizes (256
channels, 64 x 64 embedding; SAM-HQ with ViT-H's 1280-channel early features) on random
embeddings: vprflow's shared-image decoder (``vprflow.models.sam.decoder``) against a call of
the transformers model, per 1,024 prompts (one 32 x 32 grid), with peak memory growth
(CUDA: peak allocated).

Columns: ``encoder s`` = image embedding only; ``first s`` = the first full call;
``best s`` = fastest of the repeats (the first call when ``--repeats 0``); ``img/s`` =
1 / best; ``RSS MiB`` = process peak resident memory, ``+gen MiB`` = its growth during
mask generation (CUDA: peak allocated instead).
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

import numpy as np

MODELS = {
    "tiny": {
        "vision_config": {
            "hidden_size": 32,
            "output_channels": 32,
            "num_hidden_layers": 2,
            "num_attention_heads": 2,
            "image_size": 1024,
            "patch_size": 16,
            "global_attn_indexes": [1],
            "num_pos_feats": 16,
            "mlp_dim": 64,
        },
        "prompt_encoder_config": {"hidden_size": 32, "mask_input_channels": 8},
        "mask_decoder_config": {
            "hidden_size": 32,
            "mlp_dim": 64,
            "num_attention_heads": 2,
            "iou_head_hidden_dim": 32,
        },
    },
    "vit-b": {
        "vision_config": {
            "hidden_size": 768,
            "num_hidden_layers": 12,
            "num_attention_heads": 12,
            "global_attn_indexes": [2, 5, 8, 11],
        },
    },
}
_VIT_H = {"hidden_size": 1280, "num_hidden_layers": 32, "num_attention_heads": 16}
_VIT_H["global_attn_indexes"] = [7, 15, 23, 31]
# SAM 2.1 Hiera-L (sam2.1_hiera_l.yaml): embed 144, 2 heads, stages 2-6-36-4, global
# attention in blocks 23, 33, 43, windows 8-4-16-8; the rest is transformers' default.
_HIERA_L = {
    "model_type": "sam2_hiera_det_model",
    "hidden_size": 144,
    "num_attention_heads": 2,
    "blocks_per_stage": [2, 6, 36, 4],
    "embed_dim_per_stage": [144, 288, 576, 1152],
    "num_attention_heads_per_stage": [2, 4, 8, 16],
    "window_size_per_stage": [8, 4, 16, 8],
    "global_attention_blocks": [23, 33, 43],
    "window_positional_embedding_background_size": [7, 7],
}
LARGE = {
    "sam-vit-h": ("sam", "SamConfig", {"vision_config": _VIT_H}),
    "sam-hq-vit-h": (
        "sam_hq",
        "SamHQConfig",
        {"vision_config": _VIT_H, "mask_decoder_config": {"vit_dim": 1280}},
    ),
    "sam2-large": (
        "sam2",
        "Sam2Config",
        {
            "vision_config": {
                "backbone_config": _HIERA_L,
                "backbone_channel_list": [1152, 576, 288, 144],
            }
        },
    ),
}
# tests/tiny_models.py's SAM at a 64-pixel input (4 x 4 patches): what --smoke runs.
SMOKE_MODEL = "tiny-64"
FILTERS = {
    "library": {},
    "none": {"pred_iou_thresh": 0.0, "stability_score_thresh": 0.0},
}


def _rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _large_segmenter(model: str, params: dict, device: str, dtype_name: str):
    """A published-size architecture with random weights, built in memory."""
    import torch
    import transformers

    from vprflow.core.devices import resolve_device, resolve_dtype
    from vprflow.models.sam.adapters import SAM_KINDS, sam_params
    from vprflow.models.sam.generator import SamSegmenter

    kind, config_name, config = LARGE[model]
    class_name, adapter_class = SAM_KINDS[kind]
    merged = sam_params({**params, "dtype": dtype_name}, kind)
    torch_device = resolve_device(device)
    dtype = resolve_dtype(dtype_name, torch_device)
    torch.manual_seed(0)
    built = getattr(transformers, class_name)._from_config(
        getattr(transformers, config_name)(**config), attn_implementation="sdpa"
    )
    built = built.to(device=torch_device, dtype=dtype).eval()
    extra = {"hq_token_only": merged["hq_token_only"]} if kind == "sam_hq" else {}
    return SamSegmenter(adapter_class(built, torch_device, dtype, **extra), merged)


def run_one(
    model: str,
    side: int,
    filters: str,
    device: str,
    repeats: int,
    dtype: str = "float32",
    image_batches: tuple[int, ...] = (),
) -> dict:
    """One configuration in this process -> measurements (printed as JSON by main)."""
    import torch
    from transformers import SamConfig, SamModel

    from vprflow.models.sam.adapters import load_sam

    params = {"points_per_side": side, **FILTERS[filters]}
    if model in LARGE:
        segmenter = _large_segmenter(model, params, device, dtype)
    else:
        torch.manual_seed(0)
        with tempfile.TemporaryDirectory() as directory:
            if model == SMOKE_MODEL:
                sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
                from tiny_models import tiny_sam

                tiny_sam(model_size=64, scale=None).save_pretrained(directory)
            else:
                SamModel(SamConfig(**MODELS[model])).save_pretrained(directory)
            segmenter = load_sam({"model": directory, **params, "dtype": dtype}, device=device)
    image = np.random.default_rng(0).random((240, 320, 3), dtype=np.float32)
    cuda = segmenter.device.type == "cuda"

    def sync():
        if cuda:
            torch.cuda.synchronize()

    start = time.perf_counter()
    segmenter.image_embedding(image)
    sync()
    encoder = time.perf_counter() - start

    rss_before = _rss_mib()
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    times = []
    for _ in range(1 + repeats):
        start = time.perf_counter()
        masks = segmenter.masks(image)
        sync()
        times.append(time.perf_counter() - start)
    rss_after = _rss_mib()
    best = min(times[1:] or times)

    # Encoder passes over B images (generate_batch's first step; prompts are then
    # decoded image by image, so a whole image costs encoder(B) / B + the decoding).
    batches = {}
    pixels, _ = segmenter.adapter.preprocess(image)
    for size in image_batches:
        if cuda:
            torch.cuda.reset_peak_memory_stats()
        with torch.inference_mode():
            start = time.perf_counter()
            segmenter.adapter.embed(pixels.repeat(size, 1, 1, 1))
            sync()
            elapsed = time.perf_counter() - start
        peak = torch.cuda.max_memory_allocated() / 2**20 if cuda else _rss_mib()
        batches[size] = {"encoder_s": elapsed / size, "peak_mib": peak}
    return {
        "model": model,
        "side": side,
        "filters": filters,
        "dtype": dtype,
        "device": str(segmenter.device),
        "masks": int(masks.shape[0]),
        "encoder_s": encoder,
        "first_s": times[0],
        "best_s": best,
        "images_per_s": 1.0 / best,
        "rss_mib": rss_after,
        "gen_mib": (torch.cuda.max_memory_allocated() / 2**20) if cuda else rss_after - rss_before,
        "batches": batches,
    }


def decoder_one(
    kind: str, dtype_name: str, decoder: str, prompts: int, batch: int, device: str
) -> dict:
    """Time decoding ``prompts`` random points in batches of ``batch`` (this process)."""
    import torch
    import transformers

    from vprflow.core.devices import resolve_device
    from vprflow.models.sam.adapters import SAM_KINDS

    torch_device = resolve_device(device)
    cuda = torch_device.type == "cuda"

    torch.manual_seed(0)
    dtype = getattr(torch, dtype_name)
    class_name, adapter_class = SAM_KINDS[kind]
    # Smallest vision encoders (never run); decoders and prompt encoders at full size.
    tiny_vit = {"hidden_size": 32, "num_hidden_layers": 1, "num_attention_heads": 2}
    tiny_vit |= {"global_attn_indexes": [0], "mlp_dim": 64}
    if kind == "sam2":
        config = transformers.Sam2Config()
    elif kind == "sam_hq":
        config = transformers.SamHQConfig(
            vision_config=tiny_vit, mask_decoder_config={"vit_dim": 1280}
        )
    else:
        config = transformers.SamConfig(vision_config=tiny_vit)
    model = getattr(transformers, class_name)._from_config(config, attn_implementation="sdpa")
    model = model.to(device=torch_device, dtype=dtype).eval()
    adapter = adapter_class(model, torch_device, dtype, shared_decoder=decoder == "shared")
    g = torch.Generator().manual_seed(1)

    def rand(*shape):
        return torch.randn(*shape, generator=g).to(device=torch_device, dtype=dtype)

    if kind == "sam2":
        embedding = [rand(1, 32, 256, 256), rand(1, 64, 128, 128), rand(1, 256, 64, 64)]
    else:
        embedding = rand(1, 256, 64, 64)
        if kind == "sam_hq":
            embedding = (embedding, [rand(1, 64, 64, 1280)])
    points = torch.from_numpy(np.random.default_rng(0).random((prompts, 2)) * 1024.0)
    with torch.inference_mode():
        adapter.decode(embedding, points[:batch])  # warm-up
        rss_before = _rss_mib()
        if cuda:
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
        start = time.perf_counter()
        for first in range(0, prompts, batch):
            adapter.decode(embedding, points[first : first + batch])
        if cuda:
            torch.cuda.synchronize()
        elapsed = time.perf_counter() - start
    memory = torch.cuda.max_memory_allocated() / 2**20 if cuda else _rss_mib() - rss_before
    return {
        "kind": kind,
        "dtype": dtype_name,
        "decoder": decoder,
        "batch": batch,
        "s_per_1024": elapsed * 1024 / prompts,
        "ms_per_prompt": 1000 * elapsed / prompts,
        "gen_mib": memory,
    }


def _child(arguments: list[str], label: str) -> dict | None:
    """Run this script with ``arguments`` in a fresh process (its own peak memory) -> the
    JSON row it prints last, or ``None`` after printing ``label`` and its error."""
    return _children([(arguments, label)])[0]


def _children(cases: list[tuple[list[str], str]]) -> list[dict | None]:
    """Run every case's ``arguments`` in one fresh process, one after the other (so
    the later rows' peak memory includes the earlier ones': --smoke only) -> their JSON
    rows, or ``None`` for each after printing the labels and the error."""
    arguments = ["--cases", json.dumps([case for case, _ in cases])]
    output = subprocess.run([sys.executable, __file__, *arguments], capture_output=True, text=True)
    if output.returncode:
        error = (output.stderr.strip().splitlines() or ["?"])[-1]
        for _, label in cases:
            print(f"{label} failed: {error}")
        return [None] * len(cases)
    return [json.loads(line) for line in output.stdout.strip().splitlines()[-len(cases) :]]


def decoder_cases(args) -> list[tuple[list[str], str]]:
    """The decoding table's rows: each one's child arguments and its label."""
    cases = []
    for kind in args.kinds:
        for dtype in args.dtypes:
            for batch in args.points_per_batch:
                for decoder in ("transformers", "shared"):
                    arguments = ["--decoder-one", kind, dtype, decoder, str(args.prompts)]
                    arguments += [str(batch), "--device", args.device]
                    cases.append((arguments, f"{kind:7} {dtype:8} {decoder:12}"))
    return cases


def mask_cases(args) -> list[tuple[list[str], str]]:
    """The automatic-mask table's rows: each one's child arguments and its label."""
    cases = []
    for model in args.models:
        for side in args.sides:
            for dtype in args.dtypes:
                for filters in args.filters:
                    arguments = ["--one", model, str(side), filters, dtype]
                    arguments += ["--device", args.device, "--repeats", str(args.repeats)]
                    arguments += ["--image-batches", *map(str, args.image_batches)]
                    cases.append((arguments, f"{model:12} {side:>4} {filters:8} {dtype:8}"))
    return cases


def one_by_one(cases: list[tuple[list[str], str]]):
    """Each case's row from a process of its own, as it finishes (the tables print as
    they go)."""
    return (_child(arguments, label) for arguments, label in cases)


def print_table(title: str, header: str, rows, print_row) -> int:
    """``title``, ``header`` and its rule, then ``print_row(row)`` for each row that is not
    ``None`` (a failed measurement); returns how many failed."""
    print(title)
    print(header)
    print("-" * len(header))
    failed = 0
    for row in rows:
        if row is None:
            failed += 1
        else:
            print_row(row)
    return failed


def decoders_table(args, rows) -> int:
    """Print the decoding table from ``rows`` (one per :func:`decoder_cases` case, ``None``
    where it failed); returns how many measurements failed."""
    header = f"{'kind':7} {'dtype':8} {'decoder':12} {'batch':>5} {'s/1024':>7} {'ms/prompt':>9}"
    header += f" {'+mem MiB':>8}"

    def print_row(row):
        print(
            f"{row['kind']:7} {row['dtype']:8} {row['decoder']:12} {row['batch']:>5} "
            f"{row['s_per_1024']:>7.2f} {row['ms_per_prompt']:>9.2f} {row['gen_mib']:>8.0f}",
            flush=True,
        )

    title = f"SAM prompt decoding on {args.device}, random weights, per 1,024 prompts"
    return print_table(title, header, rows, print_row)


def masks_table(args, rows) -> int:
    """Print the automatic-mask table from ``rows`` (one per :func:`mask_cases` case,
    ``None`` where it failed); returns how many measurements failed."""
    header = (
        f"{'model':12} {'side':>4} {'filters':8} {'dtype':8} {'device':6} {'masks':>5} "
        f"{'encoder s':>9} {'first s':>8} {'best s':>7} {'img/s':>7} {'RSS MiB':>8} "
        f"{'+gen MiB':>8}"
    )

    def print_row(row):
        print(
            f"{row['model']:12} {row['side']:>4} {row['filters']:8} "
            f"{row['dtype']:8} {row['device']:6} {row['masks']:>5} "
            f"{row['encoder_s']:>9.2f} {row['first_s']:>8.2f} {row['best_s']:>7.2f} "
            f"{row['images_per_s']:>7.3f} {row['rss_mib']:>8.0f} "
            f"{row['gen_mib']:>8.0f}",
            flush=True,
        )
        decode = row["best_s"] - row["batches"].get("1", {}).get("encoder_s", row["encoder_s"])
        for size, batch in row["batches"].items():
            whole = batch["encoder_s"] + decode
            print(
                f"{'':12}   image batch {size:>2}: "
                f"encoder {batch['encoder_s']:.2f} s/img,"
                f" decoding {decode:.2f} s/img -> {whole:.2f} s/img"
                f" ({1 / whole:.3f} img/s), peak {batch['peak_mib']:.0f} MiB",
                flush=True,
            )

    title = "SAM automatic masks, one 320x240 image, random weights"
    return print_table(title, header, rows, print_row)


def one_case(args) -> dict:
    """The row of the one case ``args`` name (``--one`` or ``--decoder-one``), measured in
    this process."""
    if args.decoder_one:
        kind, dtype, decoder, prompts, batch = args.decoder_one
        return decoder_one(kind, dtype, decoder, int(prompts), int(batch), args.device)
    model, side, filters, dtype = args.one
    return run_one(
        model, int(side), filters, args.device, args.repeats, dtype, tuple(args.image_batches)
    )


def arguments() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    choices = [*MODELS, *LARGE, SMOKE_MODEL]
    parser.add_argument("--device", default="auto")
    parser.add_argument("--repeats", type=int, default=2, help="timed calls after the first")
    parser.add_argument("--sides", "--points-per-side", type=int, nargs="+", default=[16, 32])
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=choices)
    parser.add_argument("--dtypes", nargs="+", default=["float32"])
    parser.add_argument("--filters", nargs="+", default=list(FILTERS), choices=list(FILTERS))
    parser.add_argument("--one", nargs=4, metavar=("MODEL", "SIDE", "FILTERS", "DTYPE"))
    parser.add_argument(
        "--image-batches",
        type=int,
        nargs="*",
        default=[],
        help="also time the image encoder on batches of these many images",
    )
    parser.add_argument("--decoders", action="store_true", help="time prompt decoding only")
    parser.add_argument("--kinds", nargs="+", default=["sam", "sam_hq", "sam2"])
    parser.add_argument("--prompts", type=int, default=256, help="prompts timed (--decoders)")
    parser.add_argument("--points-per-batch", type=int, nargs="+", default=[64])
    parser.add_argument("--decoder-one", nargs=5, help=argparse.SUPPRESS)
    # A JSON list of cases' arguments (--one or --decoder-one), measured one after the
    # other in this process, a JSON row each.
    parser.add_argument("--cases", help=argparse.SUPPRESS)
    parser.add_argument(
        "--smoke", action="store_true", help="both tables at their smallest, on the CPU"
    )
    return parser


def main() -> None:
    parser = arguments()
    args = parser.parse_args()

    if args.cases:
        for case in json.loads(args.cases):
            print(json.dumps(one_case(parser.parse_args(case))), flush=True)
        return
    if args.decoder_one or args.one:
        print(json.dumps(one_case(args)))
        return
    if args.smoke:
        # Both tables, each at its smallest: the tiniest SAM on 2 x 2 prompts (all filters
        # off, so the box NMS has candidates; a batch of 2 images), timed once, then
        # decoding one batch of 2 prompts. Every row in one process, which imports
        # transformers (~4 s of CPU) once: its peak memory is not each row's own.
        args.device, args.models, args.sides = "cpu", [SMOKE_MODEL], [2]
        args.dtypes, args.filters, args.repeats, args.image_batches = ["float32"], ["none"], 0, [2]
        args.kinds, args.prompts, args.points_per_batch = ["sam"], 2, [2]
        masks, decoders = mask_cases(args), decoder_cases(args)
        rows = _children(masks + decoders)
        failed = masks_table(args, rows[: len(masks)])
        print()
        failed += decoders_table(args, rows[len(masks) :])
    elif args.decoders:
        failed = decoders_table(args, one_by_one(decoder_cases(args)))
    else:
        failed = masks_table(args, one_by_one(mask_cases(args)))
    if failed:
        sys.exit(f"{failed} measurement(s) failed")


if __name__ == "__main__":
    main()
