"""Side by side: vprflow's ResNet trunk and CNN-based trained VPR models against the
original code.

Compared: :class:`vprflow.models.trunks.resnet.ResNet` (18/34/50/101/152) against
torchvision's ``resnet<depth>`` (maps of layer1 ... layer4 and the classifier's logits,
through :func:`load_resnet` on torchvision's own state dict), CosPlace and EigenPlaces
(``cosplace_model/``, ``eigenplaces_model/``), MixVPR (``models/backbones/resnet.py``,
``models/aggregators/mixvpr.py``), Conv-AP (gsv-cities' ``models/backbones/resnet.py``,
``models/aggregators/convap.py``) and BoQ-ResNet50 (``src/backbones.py``,
``src/boq.py``). ``ORIGINALS`` holds one folder per repository (``CosPlace``,
``EigenPlaces``, ``MixVPR``, ``gsv-cities``, ``Bag-of-Queries``, e.g. extracted with
``git archive``), each with an optional ``COMMIT`` file naming repository and commit.

Each original model gets random weights (He-scaled convolutions and linears, then its
BatchNorm statistics set from one batch so that activations stay O(1) through 50+
blocks), is saved with ``torch.save`` in its own state-dict layout (the layout of the
published checkpoint: plain state dicts for CosPlace / EigenPlaces / BoQ, a
``"state_dict"`` Lightning container for MixVPR / Conv-AP to exercise that path too)
and read by vprflow's loader; both run on the same random ImageNet-normalised batch in
float32 on CPU. Printed: max |difference| of the descriptors and of the feature map the
head reads, descriptor length, input size, checkpoint layout.

    bash ../shared/tools/torchvision-for-checks.sh /tmp/tv
    PYTHONPATH=/tmp/tv python benchmarks/check_trained_cnn.py /tmp/originals_cnn
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import math
import sys
import tempfile
from pathlib import Path

import torch
from originals import commit_of, load_module
from torch import nn

from vprflow.models.trained.boq import load_boq_resnet50
from vprflow.models.trained.convap import load_convap
from vprflow.models.trained.cosplace import load_cosplace, load_eigenplaces
from vprflow.models.trained.mixvpr import load_mixvpr
from vprflow.models.trunks.resnet import LAYERS, load_resnet


def _randomise(model: nn.Module, images: torch.Tensor, seed: int) -> nn.Module:
    """Parameters re-drawn (He by fan-in; norms near 1; biases, GeM's p and queries
    perturbed), then BatchNorm running statistics taken from one pass over ``images``
    so that no layer saturates or vanishes."""
    generator = torch.Generator().manual_seed(seed)
    norms = {
        f"{name}.{leaf}"
        for name, module in model.named_modules()
        if isinstance(module, (nn.BatchNorm2d, nn.LayerNorm))
        for leaf in ("weight", "bias")
    }
    with torch.no_grad():
        for name, parameter in model.named_parameters():
            noise = torch.randn(parameter.shape, generator=generator)
            leaf = name.rpartition(".")[2]
            if leaf == "p":
                value = 3.0 + 0.3 * noise
            elif name in norms:
                value = (1.0 if leaf == "weight" else 0.0) + 0.1 * noise
            elif parameter.ndim == 1:
                value = 0.05 * noise
            elif leaf == "queries":
                value = noise
            else:
                value = noise * math.sqrt(2.0 / parameter[0].numel())
            parameter.copy_(value)
        batchnorms = [m for m in model.modules() if isinstance(m, nn.BatchNorm2d)]
        for norm in batchnorms:
            norm.reset_running_stats()
            norm.momentum = None  # cumulative: one pass sets the batch's statistics
        model.train()
        model(images)
        for norm in batchnorms:
            norm.momentum = 0.1
    return model.eval()


def _max_diff(a: torch.Tensor, b: torch.Tensor) -> tuple[float, float]:
    if a.shape != b.shape:
        raise AssertionError(f"shapes differ: {tuple(a.shape)} vs {tuple(b.shape)}")
    return float((a - b).abs().max()), float(b.abs().max())


def _save(state: dict, folder: Path, name: str, container: str | None) -> str:
    path = folder / name
    torch.save({container: state} if container else state, path)
    return str(path)


def check_trunks(depths, size, batch, seed, rows):
    import torchvision

    images = torch.randn(batch, 3, *size, generator=torch.Generator().manual_seed(seed))
    with tempfile.TemporaryDirectory() as folder:
        for depth in depths:
            reference = _randomise(getattr(torchvision.models, f"resnet{depth}")(), images, seed)
            path = _save(reference.state_dict(), Path(folder), f"resnet{depth}.pth", None)
            ours = load_resnet(path, depth, classifier=True)
            with torch.no_grad():
                x = reference.maxpool(reference.relu(reference.bn1(reference.conv1(images))))
                expected = {}
                for layer in LAYERS:
                    x = getattr(reference, layer)(x)
                    expected[layer] = x
                maps = ours.feature_maps(images, LAYERS)
                map_diff = max(_max_diff(maps[k], expected[k])[0] for k in LAYERS)
                logits, scale = _max_diff(ours(images), reference(images))
            rows.append(
                (
                    f"ResNet-{depth} trunk",
                    f"pytorch/vision {torchvision.__version__}",
                    f"{logits:.2e} (logits, max {scale:.1f})",
                    f"{map_diff:.2e} (layer1-4)",
                    "1000",
                    f"{size[0]}x{size[1]}",
                    "torchvision resnet state dict",
                )
            )


def _compare(name, source, reference, ours, images, layout, rows, reference_map, layer):
    with torch.no_grad():
        out = reference(images)
        out = out[0] if isinstance(out, tuple) else out
        descriptor, _ = _max_diff(ours(images), out)
        feature, scale = _max_diff(ours.feature_map(images, layer), reference_map(images))
    # L2 distance between two images' unit descriptors (0 to 2): a difference of 0
    # above means something only if the descriptors are not all alike.
    spread = float((out[0] - out[1]).norm())
    rows.append(
        (
            name,
            source,
            f"{descriptor:.2e} (|d0 - d1| = {spread:.3f})",
            f"{feature:.2e} ({layer}, max {scale:.1f})",
            str(out.shape[1]),
            f"{images.shape[2]}x{images.shape[3]}",
            layout,
        )
    )


class _Pair(nn.Module):
    """amaralibey's ``VPRModel`` without Lightning: ``backbone`` then ``aggregator``, the
    same attribute names and so the same state-dict keys."""

    def __init__(self, backbone: nn.Module, aggregator: nn.Module):
        super().__init__()
        self.backbone, self.aggregator = backbone, aggregator

    def forward(self, x):
        return self.aggregator(self.backbone(x))


def check_models(originals: Path, size, batch, seed, rows):
    import torchvision

    generator = torch.Generator().manual_seed(seed + 1)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)

        # CosPlace / EigenPlaces: ImageNet / CosPlace weights are downloads, replaced here.
        sys.path.insert(0, str(originals / "CosPlace"))
        cosplace_network = importlib.import_module("cosplace_model.cosplace_network")
        cosplace_network.get_pretrained_torchvision_model = lambda name: getattr(
            torchvision.models, name.lower()
        )()
        sys.path.insert(0, str(originals / "EigenPlaces"))
        eigen_network = importlib.import_module("eigenplaces_model.eigenplaces_network")
        hub_load = torch.hub.load
        torch.hub.load = lambda *args, **kwargs: nn.Module()
        variants = [
            ("CosPlace", cosplace_network.GeoLocalizationNet, load_cosplace, "cosplace", b, d)
            for b, d in (
                ("ResNet50", 2048),
                ("ResNet18", 512),
                ("ResNet101", 2048),
                ("ResNet152", 2048),
            )
        ] + [
            (
                "EigenPlaces",
                eigen_network.GeoLocalizationNet_,
                load_eigenplaces,
                "eigenplaces",
                b,
                d,
            )
            for b, d in (("ResNet50", 2048), ("ResNet18", 512), ("ResNet101", 2048))
        ]
        try:
            for method, network, loader, suffix, backbone, dim in variants:
                images = torch.randn(batch, 3, *size, generator=generator)
                reference = _randomise(network(backbone, dim), images, seed)
                path = _save(reference.state_dict(), folder, f"{backbone}_{dim}_{suffix}.pth", None)
                ours = loader(path, backbone, dim)
                repo = "CosPlace" if method == "CosPlace" else "EigenPlaces"
                _compare(
                    f"{method} {backbone}-{dim}",
                    commit_of(originals / repo),
                    reference,
                    ours,
                    images,
                    "plain state dict backbone.<i>.*, aggregation.{1.p,3.*}",
                    rows,
                    reference.backbone,
                    "layer4",
                )
        finally:
            torch.hub.load = hub_load

        # MixVPR (README configuration; a smaller head whose sizes the loader infers).
        backbones = load_module(originals / "MixVPR/models/backbones/resnet.py", "mixvpr_resnet")
        mixvpr = load_module(originals / "MixVPR/models/aggregators/mixvpr.py", "mixvpr_agg")
        for out_channels, rows_out in ((1024, 4), (128, 4)):
            images = torch.randn(batch, 3, 320, 320, generator=generator)
            reference = _Pair(
                backbones.ResNet("resnet50", pretrained=False, layers_to_crop=[4]),
                mixvpr.MixVPR(
                    1024, 20, 20, out_channels, mix_depth=4, mlp_ratio=1, out_rows=rows_out
                ),
            )
            reference = _randomise(reference, images, seed)
            path = _save(reference.state_dict(), folder, "mixvpr.ckpt", "state_dict")
            _compare(
                f"MixVPR {out_channels * rows_out}",
                commit_of(originals / "MixVPR"),
                reference,
                load_mixvpr(path),
                images,
                "Lightning 'state_dict': backbone.model.*, aggregator.*",
                rows,
                reference.backbone,
                "layer3",
            )

        # Conv-AP (gsv-cities), 4096-d and 8192-d.
        backbones = load_module(originals / "gsv-cities/models/backbones/resnet.py", "gsv_resnet")
        convap = load_module(originals / "gsv-cities/models/aggregators/convap.py", "gsv_convap")
        for out_channels in (1024, 2048):
            images = torch.randn(batch, 3, 320, 320, generator=generator)
            reference = _Pair(
                backbones.ResNet("resnet50", pretrained=False, layers_to_crop=[]),
                convap.ConvAP(2048, out_channels, 2, 2),
            )
            reference = _randomise(reference, images, seed)
            path = _save(reference.state_dict(), folder, "convap.ckpt", "state_dict")
            _compare(
                f"Conv-AP {out_channels * 4}",
                commit_of(originals / "gsv-cities"),
                reference,
                load_convap(path, out_channels * 4),
                images,
                "Lightning 'state_dict': backbone.model.*, aggregator.channel_pool.*",
                rows,
                reference.backbone,
                "layer4",
            )

        # BoQ-ResNet50 as hubconf.get_trained_boq builds it.
        boq_backbones = load_module(originals / "Bag-of-Queries/src/backbones.py", "boq_backbones")
        boq = load_module(originals / "Bag-of-Queries/src/boq.py", "boq_boq")
        images = torch.randn(batch, 3, 384, 384, generator=generator)
        backbone = boq_backbones.ResNet("resnet50", pretrained=False, crop_last_block=True)
        aggregator = boq.BoQ(backbone.out_channels, 512, 64, 2, 32)
        reference = _Pair(backbone, aggregator)
        reference = _randomise(reference, images, seed)
        path = _save(reference.state_dict(), folder, "resnet50_16384.pth", None)
        _compare(
            "BoQ-ResNet50 16384",
            commit_of(originals / "Bag-of-Queries"),
            reference,
            load_boq_resnet50(path),
            images,
            "plain state dict backbone.net.<i>.*, aggregator.*",
            rows,
            reference.backbone,
            "layer3",
        )


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("originals", type=Path, help="folder of the original repositories")
    parser.add_argument(
        "--size",
        type=int,
        nargs=2,
        default=(240, 320),
        metavar=("H", "W"),
        help="input of the trunks and CosPlace / EigenPlaces (own-size models)",
    )
    parser.add_argument("--batch", type=int, default=2, help="images per batch (at least 2)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--depths", type=int, nargs="*", default=[18, 34, 50, 101, 152])
    args = parser.parse_args(argv)
    torch.set_grad_enabled(False)
    rows: list[tuple[str, ...]] = []
    check_trunks(args.depths, tuple(args.size), args.batch, args.seed, rows)
    check_models(args.originals, tuple(args.size), args.batch, args.seed, rows)
    header = (
        "model",
        "source (repository commit)",
        "max |Δ| descriptor",
        "max |Δ| feature map",
        "dim",
        "input",
        "checkpoint layout tested",
    )
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    for row in [header, tuple("-" * w for w in widths), *rows]:
        print(" | ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)))


if __name__ == "__main__":
    main()
