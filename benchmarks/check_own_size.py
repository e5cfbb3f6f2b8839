"""Side by side: images of mixed sizes read as gmberton/VPR-methods-evaluation reads
them for MegaLoc, CosPlace and EigenPlaces, against vprflow's features stage under
``resolution: own`` (those kinds' default).

The original side: VPR-methods-evaluation's ``TestDataset`` (``test_dataset.py``: PIL
``Image.open(...).convert("RGB")``, ``ToTensor``, ``Normalize``, no ``Resize`` since
these methods set no ``--image_size``), each image alone (batch size 1, as it runs its
queries; its database batches of 4 cannot stack images of different sizes), into the
original model: MegaLoc's ``megaloc_model.MegaLoc`` (which rounds each side to a
multiple of 14 itself) and CosPlace's ``cosplace_model.cosplace_network
.GeoLocalizationNet`` (EigenPlaces builds the same network), with random weights. The
vprflow side: the images and features stages (``vprflow.stages.jobs.run_job``) of a
dataset made of the same files, the model loaded by vprflow's loader from the original's
state dict saved in the published layout, batches of ``--batch-size`` cut where the
size changes.

``ORIGINALS`` holds ``VPR-methods-evaluation``, ``MegaLoc`` and ``CosPlace`` (e.g. each
extracted with ``git archive``). The images: the first ``--pairs`` pairs of RoadScene
(``$VPRFLOW_DATA/roadscene``, ``vi/`` references, ``ir/`` queries; every pair its own
size, none a multiple of 14 on both sides). scikit-learn, which ``test_dataset.py``
imports for its ground truth, is replaced by a stand-in (no labels are read).

Printed per model: images, distinct sizes, max / mean |difference| of the model's input
in grey levels (the ImageNet-normalised tensors, times std x 255), max |difference| of
the descriptors, and for MegaLoc how many sides are off the 14-pixel grid.

    bash ../shared/tools/torchvision-for-checks.sh /tmp/tv
    PYTHONPATH=/tmp/tv VPRFLOW_DATA=../shared/data \\
        python benchmarks/check_own_size.py /tmp/originals_own [--pairs 6] [--vit-depth 12]
"""

from __future__ import annotations

import argparse
import copy
import importlib.util
import os
import shutil
import sys
import tempfile
import types
from pathlib import Path

import numpy as np
import torch
import yaml
from originals import load_module

REPO = Path(__file__).resolve().parents[1]


def _test_dataset(originals: Path) -> types.ModuleType:
    """VPR-methods-evaluation's ``test_dataset.py``, which imports ``sklearn.neighbors``
    for its positives only: a stand-in while it loads, where scikit-learn is missing."""
    path = originals / "VPR-methods-evaluation" / "test_dataset.py"
    if importlib.util.find_spec("sklearn") is not None:
        return load_module(path, "vme_test_dataset")
    import torchvision.transforms  # noqa: F401  (before the stand-in: torch reads the specs)

    sklearn = types.ModuleType("sklearn")
    sklearn.neighbors = types.ModuleType("sklearn.neighbors")
    sklearn.neighbors.NearestNeighbors = None
    sys.modules.update({"sklearn": sklearn, "sklearn.neighbors": sklearn.neighbors})
    try:
        return load_module(path, "vme_test_dataset")
    finally:
        del sys.modules["sklearn"], sys.modules["sklearn.neighbors"]


def _randomise(model: torch.nn.Module, seed: int) -> torch.nn.Module:
    """Weights of O(1 / sqrt(fan in)), LayerNorms and BatchNorms at identity, DINOv2's
    layer scales near 1 (their 1e-5 initialisation makes every block a near-identity)."""
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, parameter in model.named_parameters():
            if "norm" in name or name.rsplit(".", 2)[-2:-1] in (["bn1"], ["bn2"], ["bn3"]):
                continue
            fan_in = max(1, parameter[0].numel()) if parameter.ndim > 1 else 1
            noise = torch.randn(parameter.shape, generator=generator) / fan_in**0.5
            if name.endswith("gamma"):
                noise = 1.0 + 0.1 * noise
            parameter.copy_(noise)
    return model.eval()


def _subset(data: Path, pairs: int, work: Path) -> Path:
    folder = work / "data" / "mixed"
    for role in ("vi", "ir"):
        (folder / role).mkdir(parents=True)
        for path in sorted((data / "roadscene" / role).iterdir())[:pairs]:
            shutil.copy(path, folder / role / path.name)
    return folder


def _config(work: Path, backbone: dict) -> dict:
    from vprflow.planning.config import validate_config

    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config = copy.deepcopy(config)
    config["data_root"] = str(work / "data")
    config["targets"] = ["mixed"]
    config["datasets"] = {
        "mixed": {
            "path": "mixed",
            "reference": "vi",
            "query": "ir",
            "paired": True,
            "resolution": [224, 224],  # not read under `resolution: own`
            "ground_truth": {"kind": "pairs"},
            "methods": ["own"],
        }
    }
    config["backbones"]["own"] = backbone
    config["methods"] = {"own": {"aggregator": "model", "features": "own"}}
    return validate_config(config, REPO / "workflow" / "schemas" / "config.schema.yaml")


def _vprflow(work: Path, backbone: dict, batch_size: int, loader_options: dict):
    """Descriptors and inputs of vprflow's features stage, by image name."""
    from vprflow.core import stores
    from vprflow.models import loaders
    from vprflow.planning.plan import build_plan
    from vprflow.stages.jobs import Job, run_job
    from vprflow.stages.readers import Dataset

    plan = build_plan(_config(work, backbone))
    (features,) = plan.stages["features"].values()
    assert features.record["params"]["resolution"] == "own", features.record["params"]
    images_key = plan.images_keys["mixed"]
    root = str(work / "data")
    images = str(work / "images.zarr")
    run_job(Job(plan.get("images", images_key).record, {}, images, data_root=root))
    out = str(work / f"features-{backbone['backbone']}.zarr")
    run = {"device": "cpu", "batch_size": batch_size}
    loaded = []
    original_loader = loaders.TRAINED_MODELS[backbone["backbone"]]

    def loader(path, **options):  # the stage's model, kept to read its input too
        loaded.append(original_loader(path, **{**options, **loader_options}))
        return loaded[-1]

    loaders.TRAINED_MODELS[backbone["backbone"]] = loader
    try:
        run_job(Job(features.record, {"images": images}, out, data_root=root, run=run))
    finally:
        loaders.TRAINED_MODELS[backbone["backbone"]] = original_loader
    dataset = Dataset(images, root)
    grids = np.asarray(stores.open_store(out)["features"][...])
    names = [Path(p).parent.name + "/" + Path(p).name for p in dataset.paths]
    return dict(zip(names, grids[:, 0, 0], strict=True)), dataset


def _inputs_vprflow(dataset, backbone) -> dict[str, torch.Tensor]:
    """The tensor vprflow's adapter gives the model for each image, read as the stage
    reads it (``exif_orientation`` of a trained model's descriptor: ignore)."""
    from vprflow.models.trained.backbone import TrainedBackbone

    adapter = TrainedBackbone(backbone, "descriptor", 1, crop=False, device="cpu")
    return {
        Path(p).parent.name + "/" + Path(p).name: adapter.preprocess(
            dataset.read_image(i, "ignore")[None]
        )
        for i, p in enumerate(dataset.paths)
    }


def _inputs_original(originals: Path, folder: Path) -> dict[str, torch.Tensor]:
    ds = _test_dataset(originals).TestDataset(
        str(folder / "vi"), str(folder / "ir"), image_size=None, use_labels=False
    )
    return {
        Path(p).parent.name + "/" + Path(p).name: ds[i][0][None]
        for i, p in enumerate(ds.images_paths)
    }


def _grey_levels(a: torch.Tensor, b: torch.Tensor) -> tuple[float, float]:
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    diff = ((a - b) * std * 255).abs()
    return float(diff.max()), float(diff.mean())


def check(originals: Path, data: Path, pairs: int, depth: int, batch_size: int) -> list:
    from vprflow.models.trunks.dinov2 import dinov2_config

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        folder = _subset(data, pairs, work)
        original_inputs = _inputs_original(originals, folder)
        sizes = {tuple(x.shape[-2:]) for x in original_inputs.values()}

        megaloc = load_module(originals / "MegaLoc" / "megaloc_model.py", "megaloc_original")
        source = megaloc.MegaLoc()
        source.backbone.blocks = source.backbone.blocks[:depth]
        _randomise(source, seed=1)
        from safetensors.torch import save_file

        path = work / "model.safetensors"
        save_file({k: v.contiguous() for k, v in source.state_dict().items()}, str(path))
        models = [("MegaLoc", f"ViT-B/14, {depth} blocks", source, path, "megaloc", {})]
        if depth != 12:
            models[0][5]["config"] = dinov2_config(num_hidden_layers=depth)

        sys.path.insert(0, str(originals / "CosPlace"))
        import torchvision

        network = importlib.import_module("cosplace_model.cosplace_network")
        # ImageNet's weights are a download; the trunk is replaced by random weights.
        network.get_pretrained_torchvision_model = lambda name: getattr(
            torchvision.models, name.lower()
        )()
        cosplace = _randomise(network.GeoLocalizationNet("ResNet50", 2048), seed=2)
        path = work / "ResNet50_2048_cosplace.pth"
        torch.save(cosplace.state_dict(), path)
        models.append(("CosPlace", "ResNet50_2048", cosplace, path, "cosplace", {}))

        for name, variant, source, path, kind, options in models:
            entry = {"backbone": kind, "checkpoint": str(path)}
            ours, dataset = _vprflow(work, entry, batch_size, options)
            with torch.no_grad():
                published = {k: source(x)[0].numpy() for k, x in original_inputs.items()}
            from vprflow.models.loaders import TRAINED_MODELS

            ours_inputs = _inputs_vprflow(dataset, TRAINED_MODELS[kind](str(path), **options))
            pixels = [_grey_levels(original_inputs[k], ours_inputs[k]) for k in ours]
            off = sum(s % 14 != 0 for size in sizes for s in size)
            rows.append(
                {
                    "model": f"{name} ({variant})",
                    "images": len(ours),
                    "sizes": len(sizes),
                    "grey max": max(p[0] for p in pixels),
                    "grey mean": float(np.mean([p[1] for p in pixels])),
                    "descriptor max |diff|": max(
                        float(np.abs(ours[k] - published[k]).max()) for k in ours
                    ),
                    "sides off 14": f"{off} of {2 * len(sizes)}" if kind == "megaloc" else "-",
                }
            )
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("originals", type=Path, help="VPR-methods-evaluation, MegaLoc, CosPlace")
    parser.add_argument("--pairs", type=int, default=6, help="RoadScene pairs (6: 12 images)")
    parser.add_argument("--vit-depth", type=int, default=12, help="MegaLoc's ViT blocks (12)")
    parser.add_argument("--batch-size", type=int, default=4, help="vprflow's batch (4)")
    args = parser.parse_args(argv)
    data = Path(os.environ.get("VPRFLOW_DATA", REPO / "data"))
    torch.manual_seed(0)
    rows = check(args.originals, data, args.pairs, args.vit_depth, args.batch_size)
    print(f"torch {torch.__version__}, CPU float32")
    header = list(rows[0])
    print(" | ".join(header))
    for row in rows:
        print(
            " | ".join(
                f"{row[h]:.3g}" if isinstance(row[h], float) else str(row[h]) for h in header
            )
        )


if __name__ == "__main__":
    main()
