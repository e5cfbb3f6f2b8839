"""SALAD in float32 (vprflow) against SALAD under float16 autocast (its published
evaluation), random weights.

SALAD's ``eval.py`` (serizba/salad) computes every descriptor inside
``torch.autocast(device_type='cuda', dtype=torch.float16)`` (and ``torch.no_grad``):
convolutions, linear layers and matrix products run in float16, the ops autocast keeps
in float32 (softmax, layer norm, exp, normalize, ...) in float32. vprflow runs the
model in float32. This check runs vprflow's SALAD (:mod:`vprflow.models.trained.salad`,
full size, random weights: O(1 / sqrt(fan in)), DINOv2's layer scales near 1) both ways
on the same images and prints how far the descriptors move and how often the ranking
moves: each query's nearest reference (inner product, as faiss's flat index on unit
vectors) and its top 5, float16-autocast against float32.

Images: the first ``--pairs`` reference / query pairs of corridor
(``$VPRFLOW_DATA/corridor``, ``ref/`` and ``query/``), read as vprflow reads them for
SALAD (PIL pixels, antialiased bilinear to 322 x 322, ImageNet-normalised).
``--device cuda`` is the published setting; on the CPU torch's float16 autocast runs the
same op list with CPU kernels, so the CPU row is a CPU number, not the published GPU
one. vprflow's DINOv2 is transformers' (``sdpa`` attention), SALAD's the torch-hub
DINOv2: under autocast their attention rounds differently, so the printed difference is
float16 autocast's effect on this computation, not the authors' bits.

    VPRFLOW_DATA=../shared/data python benchmarks/check_salad_autocast.py --device cuda
    VPRFLOW_DATA=../shared/data python benchmarks/check_salad_autocast.py --device cpu --pairs 20
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]


def randomise(model: torch.nn.Module, seed: int) -> torch.nn.Module:
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, parameter in model.named_parameters():
            if "norm" in name:
                continue
            fan_in = max(1, parameter[0].numel()) if parameter.ndim > 1 else 1
            noise = torch.randn(parameter.shape, generator=generator) / fan_in**0.5
            if "lambda1" in name:  # layer scales: 1e-5 at init makes blocks identities
                noise = 1.0 + 0.1 * noise
            parameter.copy_(noise)
    return model.eval()


def corridor_pixels(data: Path, pairs: int) -> torch.Tensor:
    from vprflow.data.images import read_image, resize_image
    from vprflow.models.trained.salad import INPUT_SIZE, MEAN, STD

    height, width = INPUT_SIZE
    images = []
    for role in ("ref", "query"):
        paths = sorted((data / "corridor" / role).iterdir())[:pairs]
        images += [resize_image(read_image(p, "ignore"), width, height, "antialias") for p in paths]
    x = torch.from_numpy(np.stack(images)).permute(0, 3, 1, 2)
    return (x - torch.tensor(MEAN).view(1, 3, 1, 1)) / torch.tensor(STD).view(1, 3, 1, 1)


def descriptors(model, pixels, device, batch: int, autocast: bool) -> tuple[np.ndarray, float]:
    out, start = [], time.perf_counter()
    with torch.no_grad(), torch.autocast(device.type, dtype=torch.float16, enabled=autocast):
        for i in range(0, len(pixels), batch):
            out.append(model(pixels[i : i + batch].to(device)).float().cpu())
    return torch.cat(out).numpy(), (time.perf_counter() - start) / len(pixels)


def compare(d32: np.ndarray, d16: np.ndarray, pairs: int) -> dict:
    refs32, queries32, refs16, queries16 = d32[:pairs], d32[pairs:], d16[:pairs], d16[pairs:]
    rank32 = np.argsort(-(queries32 @ refs32.T), axis=1, kind="stable")
    rank16 = np.argsort(-(queries16 @ refs16.T), axis=1, kind="stable")
    k = min(5, pairs)
    top5 = [len(set(a[:k]) & set(b[:k])) / k for a, b in zip(rank32, rank16, strict=True)]
    cosine = np.sum(d32 * d16, axis=1) / (np.linalg.norm(d32, axis=1) * np.linalg.norm(d16, axis=1))
    return {
        "max |diff|": float(np.abs(d32 - d16).max()),
        "mean |diff|": float(np.abs(d32 - d16).mean()),
        "max 1 - cosine": float(1.0 - cosine.min()),
        "top-1 same": f"{int((rank32[:, 0] == rank16[:, 0]).sum())} of {len(rank32)}",
        "top-5 overlap": float(np.mean(top5)),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    parser.add_argument("--pairs", type=int, default=111, help="corridor pairs (111: all)")
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--vit-depth", type=int, default=12, help="DINOv2 blocks (12)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    from vprflow.models.trained.salad import SALAD
    from vprflow.models.trunks.dinov2 import dinov2_config

    name = args.device
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    device = torch.device(name)
    data = Path(os.environ.get("VPRFLOW_DATA", REPO / "data"))
    pixels = corridor_pixels(data, args.pairs)
    model = SALAD(dinov2_config(num_hidden_layers=args.vit_depth))
    model = randomise(model, args.seed).to(device)
    d32, t32 = descriptors(model, pixels, device, args.batch, autocast=False)
    d16, t16 = descriptors(model, pixels, device, args.batch, autocast=True)
    where = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    print(
        f"SALAD (ViT-B/14, {args.vit_depth} blocks, random weights, seed {args.seed}) on "
        f"{where}, torch {torch.__version__}: {args.pairs} corridor pairs at 322 x 322"
    )
    print(f"float32 {t32 * 1e3:.1f} ms/image, float16 autocast {t16 * 1e3:.1f} ms/image")
    for key, value in compare(d32, d16, args.pairs).items():
        print(f"{key}: {value:.3g}" if isinstance(value, float) else f"{key}: {value}")


if __name__ == "__main__":
    main()
