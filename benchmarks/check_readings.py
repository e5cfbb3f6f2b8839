"""Side by side: the image each trained model receives from vprflow's features stage and
from its authors' evaluation transform, on the same photos.

vprflow's side is the exact tensor the features stage hands the model: the shipped
config (config/config.yaml, then config/trained.yaml, merged as Snakemake merges them)
is planned, and each trained method's features stage runs
(:func:`vprflow.stages.features.compute_features`, one image a job) with the model's
loader replaced by a stand-in that keeps its input (ImageNet-normalised, cropped as the
adapter crops) and returns zeros; so whatever the stage's reading does (resolution,
resize method, EXIF orientation, crop, per-image sizes) is what is measured.

The authors' side is written as their evaluation code states it, each step citing the
file and line of ``ORIGINALS/<repository>`` it follows (checked here: the cited line
must hold the quoted text), run with torchvision (importable for checks only:
``bash ../shared/tools/torchvision-for-checks.sh /tmp/tv``, then ``PYTHONPATH=/tmp/tv``).
``ORIGINALS`` holds one folder per repository (``Patch-NetVLAD``, ``salad``,
``Bag-of-Queries``, ``MixVPR``, ``gsv-cities``, ``VPR-methods-evaluation``,
``CosPlace``, ``EigenPlaces``, ``SNSM``, ``VLAD-BuFF``), e.g. extracted with
``git archive``, each with an optional ``COMMIT`` file naming repository and commit.

Photos: the first two references and the first query of corridor (160 x 120) and of
roadscene (RGB references and grayscale thermal queries of mixed sizes), as
``--data`` holds them; each model at its shipped reading, and a second row per model at
a resolution other than its default (``NON_DEFAULT``). Printed per model and dataset:
the sizes each side feeds, and the max and mean absolute difference of the two tensors
in grey levels (each channel's difference times its std times 255; 0 where equal).
Where the authors' code would not run on an image (a grayscale image where it skips
``convert("RGB")``) the image is converted to RGB on their side, as vprflow reads it,
and the row says so.

    PYTHONPATH=/tmp/tv python benchmarks/check_readings.py /tmp/originals \\
        --data ../shared/data
"""

from __future__ import annotations

import argparse
import importlib
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import torch
import yaml
from PIL import Image
from torch import nn

REPO = Path(__file__).resolve().parents[1]
SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"
IMAGENET = ([0.485, 0.456, 0.406], [0.229, 0.224, 0.225])

# The shipped trained methods (config/trained.yaml) and the vprflow module whose MEAN /
# STD each kind's model normalises with (resnet50: the adapter's ImageNet default).
METHODS = (
    "netvlad",
    "salad",
    "vlad_buff",
    "boq_dinov2",
    "boq_resnet50",
    "megaloc",
    "mixvpr",
    "convap",
    "cosplace",
    "eigenplaces",
    "resnet50_vlad",
    "salad_tokens_vlad",
)
MODULES = {
    "netvlad": "netvlad",
    "salad": "salad",
    "vlad_buff": "vlad_buff",
    "boq_dinov2": "boq_dinov2",
    "boq_resnet50": "boq",
    "megaloc": "megaloc",
    "mixvpr": "mixvpr",
    "convap": "convap",
    "cosplace": "cosplace",
    "eigenplaces": "cosplace",
}
# A resolution other than the shipped default, per method ([width, height]); MixVPR's
# mixer fixes its input (320 x 320), so it has none.
NON_DEFAULT = {
    "netvlad": [320, 240],
    "salad": [224, 224],
    "vlad_buff": [224, 224],
    "boq_dinov2": [224, 224],
    "boq_resnet50": [320, 320],
    "megaloc": [322, 322],
    "convap": [480, 360],
    "cosplace": [512, 384],
    "eigenplaces": [512, 384],
    "resnet50_vlad": [320, 240],
    "salad_tokens_vlad": [224, 224],
}
N_REFERENCES, N_QUERIES = 2, 1


@dataclass(frozen=True)
class Cite:
    """A line of an original repository's file, and text it must hold."""

    repo: str
    path: str
    line: int
    text: str

    def check(self, originals: Path) -> str:
        lines = (originals / self.repo / self.path).read_text(errors="replace").splitlines()
        if self.text not in lines[self.line - 1]:
            raise SystemExit(f"{self.repo}/{self.path}:{self.line} no longer holds {self.text!r}")
        return f"{self.repo}/{self.path}:{self.line}"


# ------------------------------------------------------------------ the authors' side


def _transforms():
    import torchvision.transforms as T

    return T


def _open(path: Path, convert: bool) -> tuple[Image.Image, bool]:
    """``Image.open`` as the original does (``convert``: with ``.convert("RGB")``); a
    grayscale image it would feed as one channel is converted, and flagged."""
    image = Image.open(path)
    if convert or image.mode != "RGB":
        return image.convert("RGB"), not convert and image.mode != "RGB"
    return image, False


def _pil_resize_then_normalise(size_hw, interpolation):
    T = _transforms()
    steps = [] if size_hw is None else [T.Resize(size_hw, interpolation=interpolation)]
    return T.Compose([*steps, T.ToTensor(), T.Normalize(*IMAGENET)])


def authors(method: str, resolution, path: Path):
    """``(normalised tensor [3, H, W], what was done, cited lines, converted flag)``:
    the authors' evaluation reading of ``path`` at ``resolution`` ([width, height]
    or None: as published)."""
    T = _transforms()
    size = None if resolution in (None, "own", "dataset") else (resolution[1], resolution[0])
    if method == "netvlad":
        cites = [
            Cite(
                "Patch-NetVLAD", "patchnetvlad/tools/datasets.py", 42, "transforms.Resize(resize)"
            ),
            Cite("Patch-NetVLAD", "patchnetvlad/tools/datasets.py", 87, "Image.open"),
        ]
        image, flag = _open(path, convert=False)
        transform = _pil_resize_then_normalise(size or (480, 640), T.InterpolationMode.BILINEAR)
        what = f"PIL bilinear to {size or (480, 640)} (performance.ini's 480 x 640)"
    elif method in ("salad", "salad_tokens_vlad"):
        cites = [
            Cite(
                "salad",
                "eval.py",
                24,
                "T.Resize(image_size,  interpolation=T.InterpolationMode.BILINEAR)",
            ),
            Cite("salad", "README.md", 50, "--image_size 322 322"),
            Cite("salad", "dataloaders/val/PittsburghDataset.py", 45, "Image.open("),
        ]
        image, flag = _open(path, convert=False)
        transform = _pil_resize_then_normalise(size or (322, 322), T.InterpolationMode.BILINEAR)
        what = f"PIL bilinear to {size or (322, 322)}"
    elif method == "vlad_buff":
        cites = [
            Cite(
                "VLAD-BuFF",
                "eval.py",
                49,
                "T.Resize(image_size, interpolation=T.InterpolationMode.BILINEAR)",
            ),
            Cite("VLAD-BuFF", "eval.py", 240, "default=[322, 322]"),
            Cite("VLAD-BuFF", "dataloaders/val/PittsburghDataset.py", 48, "Image.open("),
        ]
        image, flag = _open(path, convert=False)
        transform = _pil_resize_then_normalise(size or (322, 322), T.InterpolationMode.BILINEAR)
        what = f"PIL bilinear to {size or (322, 322)}"
    elif method in ("boq_dinov2", "boq_resnet50"):
        cites = [
            Cite(
                "Bag-of-Queries",
                "README.md",
                49,
                "T.Resize(image_size, interpolation=T.InterpolationMode.BICUBIC, antialias=True)",
            )
        ]
        image, flag = _open(path, convert=True)
        default = (322, 322) if method == "boq_dinov2" else (384, 384)
        transform = T.Compose(
            [
                T.ToTensor(),
                T.Resize(
                    size or default, interpolation=T.InterpolationMode.BICUBIC, antialias=True
                ),
                T.Normalize(*IMAGENET),
            ]
        )
        what = f"tensor bicubic antialiased to {size or default}"
    elif method == "mixvpr":
        cites = [
            Cite(
                "MixVPR",
                "dataloaders/GSVCitiesDataloader.py",
                83,
                "T.Resize(image_size, interpolation=T.InterpolationMode.BILINEAR)",
            ),
            Cite("MixVPR", "dataloaders/PittsburgDataset.py", 109, "Image.open("),
        ]
        image, flag = _open(path, convert=False)
        transform = _pil_resize_then_normalise(size or (320, 320), T.InterpolationMode.BILINEAR)
        what = f"PIL bilinear to {size or (320, 320)}"
    elif method == "convap":
        cites = [
            Cite(
                "gsv-cities",
                "dataloaders/GSVCitiesDataloader.py",
                86,
                "T.Resize(image_size, interpolation=T.InterpolationMode.BILINEAR)",
            ),
            Cite("gsv-cities", "dataloaders/val/PittsburghDataset.py", 46, "Image.open("),
        ]
        image, flag = _open(path, convert=False)
        transform = _pil_resize_then_normalise(size or (320, 320), T.InterpolationMode.BILINEAR)
        what = f"PIL bilinear to {size or (320, 320)}"
    elif method == "megaloc" or (method in ("cosplace", "eigenplaces") and size):
        # MegaLoc's evaluation, and CosPlace's / EigenPlaces' at a chosen size: VPR-methods-
        # evaluation (--image_size H W resizes the normalised tensor).
        cites = [
            Cite(
                "VPR-methods-evaluation",
                "test_dataset.py",
                106,
                "transforms.Resize(size=image_size, antialias=True)",
            ),
            Cite(
                "VPR-methods-evaluation",
                "test_dataset.py",
                111,
                'Image.open(image_path).convert("RGB")',
            ),
        ]
        image, flag = _open(path, convert=True)
        steps = [T.ToTensor(), T.Normalize(*IMAGENET)]
        if size:
            steps.append(T.Resize(size=size, antialias=True))
        transform = T.Compose(steps)
        what = "own size" if size is None else f"normalised tensor, bilinear antialiased to {size}"
    elif method == "cosplace":
        cites = [
            Cite("CosPlace", "datasets/test_dataset.py", 41, "if resize_test_imgs:"),
            Cite("CosPlace", "datasets/test_dataset.py", 52, 'Image.open(path).convert("RGB")'),
        ]
        image, flag = _open(path, convert=True)
        transform = T.Compose([T.ToTensor(), T.Normalize(*IMAGENET)])
        what = "own size"
    elif method == "eigenplaces":
        cites = [
            Cite("EigenPlaces", "datasets/test_dataset.py", 52, "transforms.ToTensor(),"),
            Cite("EigenPlaces", "datasets/test_dataset.py", 58, "pil_img = Image.open(image_path)"),
        ]
        image, flag = _open(path, convert=False)
        transform = T.Compose([T.ToTensor(), T.Normalize(*IMAGENET)])
        what = "own size"
    elif method == "resnet50_vlad":
        cites = [
            Cite("SNSM", "SNSM/datasets_original.py", 19, "transforms.Resize(resize)"),
            Cite(
                "SNSM",
                "SNSM/datasets_original.py",
                70,
                "Image.open(self.images[index]).convert('RGB')",
            ),
        ]
        image, flag = _open(path, convert=True)
        transform = _pil_resize_then_normalise(size or (224, 224), T.InterpolationMode.BILINEAR)
        what = f"PIL bilinear to {size or (224, 224)}"
    else:
        raise ValueError(method)
    return transform(image), what, cites, flag


# ------------------------------------------------------------------ vprflow's side


class _Recorder(nn.Module):
    """Stands in for a trained model: keeps each input, returns zeros."""

    def __init__(self, mean, std, seen: list):
        super().__init__()
        self.mean, self.std, self.seen = mean, std, seen

    def forward(self, pixels):
        self.seen.append(pixels.detach().clone())
        return torch.zeros(len(pixels), 8)

    def feature_map(self, pixels, layer=None):
        self.seen.append(pixels.detach().clone())
        return torch.zeros(len(pixels), 4, 2, 2)


def _stand_ins(seen: list) -> None:
    """Every trained kind's loader replaced by one building a :class:`_Recorder` with
    the normalisation of the kind's vprflow module."""
    from vprflow.models import loaders

    def loader(kind):
        module = MODULES.get(kind)
        mean, std = IMAGENET
        if module:
            found = importlib.import_module(f"vprflow.models.trained.{module}")
            mean, std = list(found.MEAN), list(found.STD)

        def load(checkpoint, **options):
            return _Recorder(mean, std, seen)

        return load

    for kind in list(loaders.TRAINED_MODELS):
        loaders.TRAINED_MODELS[kind] = loader(kind)


def _config(data: Path, checkpoint: Path) -> dict:
    """config/config.yaml with config/trained.yaml over it (mappings key by key, lists
    replaced, as Snakemake merges config files), every checkpoint the stand-in file,
    the trained methods on corridor and roadscene, and each at a non-default size."""
    from vprflow.planning.plan import deep_merge

    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config = deep_merge(config, yaml.safe_load((REPO / "config" / "trained.yaml").read_text()))
    config["data_root"] = str(data)
    config["trained_baselines"] = False
    for entry in config["backbones"].values():
        if "checkpoint" in entry:
            entry["checkpoint"] = str(checkpoint)
    names = list(METHODS)
    for method, size in NON_DEFAULT.items():
        settings = config["methods"][method]
        backbone = f"{settings['features']}_at_{size[0]}x{size[1]}"
        config["backbones"][backbone] = {
            **config["backbones"][settings["features"]],
            "resolution": size,
        }
        config["methods"][f"{method}_at_{size[0]}x{size[1]}"] = {**settings, "features": backbone}
        names.append(f"{method}_at_{size[0]}x{size[1]}")
    for dataset in ("corridor", "roadscene"):
        config["datasets"][dataset]["methods"] = names
        config["datasets"][dataset]["rerank"] = {}
    return config


def vprflow_readings(data: Path, work: Path):
    """``{(dataset, method): (features params, [(image path, tensor [3, H, W])])}``."""
    from vprflow.planning.config import validate_config
    from vprflow.planning.plan import build_plan
    from vprflow.stages.base import Job
    from vprflow.stages.dataset import build_images
    from vprflow.stages.features import compute_features
    from vprflow.stages.readers import Dataset

    checkpoint = work / "stand-in.ckpt"
    checkpoint.write_bytes(b"stand-in")
    config = validate_config(_config(data, checkpoint), SCHEMA)
    plan = build_plan(config)
    seen: list = []
    _stand_ins(seen)
    readings = {}
    for dataset in ("corridor", "roadscene"):
        images = plan.get("images", plan.images_keys[dataset])
        images_path = str(work / f"images-{dataset}.zarr")
        build_images(Job(images.record, {}, images_path, data_root=str(data)))
        store = Dataset(images_path, str(data))
        picks = [*range(N_REFERENCES), *range(store.n_reference, store.n_reference + N_QUERIES)]
        for run in plan.runs[dataset]:
            recall = plan.get("recall", run.recall_key)
            descriptors = plan.get(*recall.inputs["descriptors"])
            features = plan.get(*descriptors.inputs["features"])
            tensors = []
            for index in picks:
                seen.clear()
                out = str(work / f"features-{dataset}-{run.method}-{index}.zarr")
                job = Job(
                    features.record,
                    {"images": images_path},
                    out,
                    start=index,
                    stop=index + 1,
                    data_root=str(data),
                    run={"device": "cpu", "batch_size": 1},
                )
                compute_features(job)
                (tensor,) = seen
                tensors.append((Path(store.paths[index]), tensor[0]))
            readings[dataset, run.method] = (features.record["params"], tensors)
    return readings


# ------------------------------------------------------------------ the table


def grey_levels(ours: torch.Tensor, theirs: torch.Tensor) -> tuple[float, float]:
    """Max and mean |difference| in 0-255 grey levels of two ImageNet-normalised images."""
    std = torch.tensor(IMAGENET[1], dtype=torch.float64).view(3, 1, 1)
    difference = (ours.double() - theirs.double()).abs() * std * 255.0
    return float(difference.max()), float(difference.mean())


def _levels(high: float, mean: float) -> str:
    """``max / mean``; 0 where the tensors are equal."""
    return "0" if high == 0 else f"{high:.2f} / {mean:.3f}"


def _size(tensor: torch.Tensor) -> str:
    return f"{tensor.shape[2]}x{tensor.shape[1]}"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("originals", type=Path, help="one folder per original repository")
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    args = parser.parse_args(argv)
    originals, data = args.originals.resolve(), args.data.resolve()
    with tempfile.TemporaryDirectory(prefix="check-readings-") as folder:
        readings = vprflow_readings(data, Path(folder))
    commits = {
        p.name: (p / "COMMIT").read_text().strip()
        for p in sorted(originals.iterdir())
        if (p / "COMMIT").is_file()
    }
    print("originals:", "; ".join(commits.values()) or "(no COMMIT files)")
    print(
        "| method | dataset | vprflow reads | authors' transform | sizes fed (vprflow; authors) "
        "| max / mean grey-level difference |"
    )
    print("|---|---|---|---|---|---|")
    cited = set()
    for (dataset, method), (params, tensors) in readings.items():
        base = method.split("_at_")[0]
        resolution = params["resolution"]
        chosen = resolution if "_at_" in method else None
        worst, total, count, sizes, flags = 0.0, 0.0, 0, [], 0
        for path, ours in tensors:
            theirs, what, cites, flag = authors(base, chosen, path)
            cited.update(c.check(originals) for c in cites)
            flags += flag
            ours_size, their_size = _size(ours), _size(theirs)
            sizes.append(ours_size if ours_size == their_size else f"{ours_size}; {their_size}")
            if ours.shape != theirs.shape:
                worst = float("nan")
                continue
            high, mean = grey_levels(ours, theirs)
            worst = max(worst, high)
            total, count = total + mean * ours.numel(), count + ours.numel()
        read = f"{resolution}, {params['resize']}, EXIF {params['exif_orientation']}"
        note = f" ({flags} grayscale image converted to RGB here)" if flags else ""
        shown = sorted(set(sizes))
        sizes_text = ", ".join(shown) if len(shown) <= 3 else f"{len(shown)} sizes"
        difference = "sizes differ" if worst != worst else _levels(worst, total / count)
        print(f"| {method} | {dataset} | {read} | {what}{note} | {sizes_text} | {difference} |")
    print("cited:", ", ".join(sorted(cited)))


if __name__ == "__main__":
    sys.exit(main())
