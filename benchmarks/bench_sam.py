"""Time and memory of Segment Anything automatic mask generation per image.

Random-weight models only (no pretrained weights here): a tiny SAM and one with the real
ViT-B architecture (hidden 768, 12 layers, 12 heads, global attention in blocks 2, 5, 8,
11, 1024 input). Each configuration runs in a fresh subprocess so its peak RSS is its
own. Two filter settings: the library thresholds (with random ViT-B weights almost no
candidate survives them, so NMS is trivial) and all filters off (every candidate reaches
the box NMS: the post-processing worst case).

    python benchmarks/bench_sam.py [--device cpu] [--repeats 2] [--sides 16 32]

Columns: ``encoder s`` = image embedding only; ``first s`` = the first full call;
``best s`` = fastest of the repeats; ``RSS MiB`` = process peak resident memory,
``+gen MiB`` = its growth during mask generation (CUDA: peak allocated instead).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time

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
FILTERS = {
    "library": {},
    "none": {"pred_iou_thresh": 0.0, "stability_score_thresh": 0.0},
}


def _rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def run_one(model: str, side: int, filters: str, device: str, repeats: int) -> dict:
    """One configuration in this process -> measurements (printed as JSON by main)."""
    import torch
    from transformers import SamConfig, SamModel

    from vprflow.sam import load_sam

    torch.manual_seed(0)
    with tempfile.TemporaryDirectory() as directory:
        SamModel(SamConfig(**MODELS[model])).save_pretrained(directory)
        params = {"model": directory, "points_per_side": side, **FILTERS[filters]}
        segmenter = load_sam(params, device=device)
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
    return {
        "model": model,
        "side": side,
        "filters": filters,
        "device": str(segmenter.device),
        "masks": int(masks.shape[0]),
        "encoder_s": encoder,
        "first_s": times[0],
        "best_s": min(times[1:] or times),
        "rss_mib": rss_after,
        "gen_mib": (torch.cuda.max_memory_allocated() / 2**20) if cuda else rss_after - rss_before,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="auto")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--sides", type=int, nargs="+", default=[16, 32])
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=list(MODELS))
    parser.add_argument("--one", nargs=3, metavar=("MODEL", "SIDE", "FILTERS"), help="internal")
    args = parser.parse_args()

    if args.one:
        model, side, filters = args.one
        print(json.dumps(run_one(model, int(side), filters, args.device, args.repeats)))
        return

    header = (
        f"{'model':6} {'side':>4} {'filters':8} {'device':6} {'masks':>5} {'encoder s':>9} "
        f"{'first s':>8} {'best s':>7} {'RSS MiB':>8} {'+gen MiB':>8}"
    )
    print("SAM automatic masks, one 320x240 image, random weights")
    print(header)
    print("-" * len(header))
    for model in args.models:
        for side in args.sides:
            for filters in FILTERS:
                command = [sys.executable, __file__, "--one", model, str(side), filters]
                command += ["--device", args.device, "--repeats", str(args.repeats)]
                output = subprocess.run(command, check=True, capture_output=True, text=True)
                row = json.loads(output.stdout.strip().splitlines()[-1])
                print(
                    f"{row['model']:6} {row['side']:>4} {row['filters']:8} {row['device']:6} "
                    f"{row['masks']:>5} {row['encoder_s']:>9.2f} {row['first_s']:>8.2f} "
                    f"{row['best_s']:>7.2f} {row['rss_mib']:>8.0f} {row['gen_mib']:>8.0f}",
                    flush=True,
                )


if __name__ == "__main__":
    main()
