"""Side by side: config/trained.yaml's ``resnet50_vlad`` (aggregator ``vlad`` on the
``resnet50`` trunk's layer3) against SNSM's ``All-Backbones-VLAD_bl.py --vlad
--backbone=ResNet50 --encoder=3`` (lfovia/SNSM), on the same photos.

``SNSM`` is the repository's folder (a clone, or ``git archive HEAD SNSM | tar -x``),
holding ``SNSM/``; its commit is read from its ``.git`` or a ``COMMIT`` file. Its modules are
imported as they are; the two its checked functions never call (``pytorch_lightning``,
``sklearn``) are stubbed where not installed. Needs torchvision, einops, lpips and
fast_pytorch_kmeans importable (checks only, never vprflow's dependencies).

1. Pixels fed to the trunk, in grey levels (x 255, before ImageNet's normalisation):
   SNSM's ``PlaceDataset`` (``PIL.Image.open(...).convert('RGB')``, its
   ``input_transform``: ``Resize((224, 224))``, ``ToTensor``) against vprflow's reader
   as the plan sets it for the row (EXIF ignored, ``antialias`` to 224 x 224), and
   against the reader the row had before (EXIF applied, ``linear``, here at 224 x 224:
   at the dataset's own resolution the grids do not even have the same size). Every
   photo of the datasets given, plus a copy of the first one tagged EXIF Orientation 6.
2. Descriptors on ``--dataset`` (its first ``--images`` references, then queries): one
   torchvision ResNet-50 with random weights (BatchNorm statistics from one batch, as
   check_trained_cnn.py draws them) run by SNSM's ``ResNet50`` and ``feature_extraction`` (its
   ``lpips.normalize_tensor`` over the tokens) and by vprflow's loader from the same
   state dict saved in torchvision's layout; SNSM's ``VLAD`` class and vprflow's
   ``vlad_descriptor`` given the same 16 centres (vprflow's spherical k-means of the
   channel-normalised reference tokens, as the vocabulary stage fits them). Printed:
   max |difference| of the normalised tokens and of the VLAD vectors, now and with
   the row's former reading (``linear`` resize, per-patch L2 only).

    git clone -q https://github.com/lfovia/SNSM /tmp/snsm
    bash ../shared/tools/torchvision-for-checks.sh /tmp/tv
    pip install -q --no-deps --target /tmp/snsmdeps einops lpips fast_pytorch_kmeans==0.2.2
    OMP_NUM_THREADS=1 PYTHONPATH=/tmp/tv:/tmp/snsmdeps \\
        python benchmarks/check_snsm_vlad.py /tmp/snsm --data ../shared/data
"""

from __future__ import annotations

import argparse
import importlib.machinery
import importlib.util
import sys
import tempfile
import types
from argparse import Namespace
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from vprflow.aggregation.aggregators import vlad_descriptor
from vprflow.aggregation.snsm import normalize_tokens
from vprflow.aggregation.vlad import fit_spherical_kmeans
from vprflow.data.images import read_image, resize_image
from vprflow.models.loaders import load_model

SIZE = 224
N_CLUSTERS = 16
SUFFIXES = {".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff"}


def _stub_missing(name: str, **attributes) -> None:
    """A stand-in for a package the checked functions never call (only imported)."""
    top = name.split(".")[0]
    if top not in sys.modules and importlib.util.find_spec(top) is not None:
        return
    parts = name.split(".")
    for i in range(len(parts)):
        stub = types.ModuleType(".".join(parts[: i + 1]))
        stub.__spec__ = importlib.machinery.ModuleSpec(stub.__name__, None)
        sys.modules.setdefault(stub.__name__, stub)
    for key, value in attributes.items():
        setattr(sys.modules[name], key, value)


def _snsm_modules(folder: Path):
    code = folder / "SNSM"
    sys.path.insert(0, str(code))
    _stub_missing("pytorch_lightning")
    _stub_missing("sklearn.neighbors", NearestNeighbors=object)
    _stub_missing("sklearn.decomposition", PCA=object)
    import datasets_original
    import vlad_utilities_hdf5

    spec = importlib.util.spec_from_file_location("snsm_bl", code / "All-Backbones-VLAD_bl.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    return datasets_original, vlad_utilities_hdf5, script


def _photos(data: Path, datasets: list[str]) -> list[Path]:
    return [
        p
        for name in datasets
        for p in sorted((data / name).rglob("*"))
        if p.suffix.lower() in SUFFIXES
    ]


def _exif_turned_copy(photo: Path, folder: Path) -> Path:
    """The photo re-saved with EXIF Orientation 6 (a phone's upright portrait)."""
    image = Image.open(photo).convert("RGB")
    exif = Image.Exif()
    exif[0x0112] = 6
    path = folder / "exif6.jpg"
    image.save(path, exif=exif.tobytes(), quality=95)
    return path


def _snsm_pixels(datasets_original, path: Path) -> np.ndarray:
    """SNSM's PlaceDataset reading before Normalize, ``[224, 224, 3]`` in [0, 1]."""
    to_tensor = datasets_original.input_transform().transforms[:2]  # Resize, ToTensor
    image = Image.open(path).convert("RGB")
    for transform in to_tensor:
        image = transform(image)
    return image.permute(1, 2, 0).numpy()


def _vprflow_pixels(path: Path, exif: str, resize: str) -> np.ndarray:
    return resize_image(read_image(path, exif), SIZE, SIZE, resize).astype(np.float32)


def compare_pixels(datasets_original, photos: list[Path], turned: Path) -> None:
    print(f"\npixels fed to the trunk, grey levels: {len(photos)} photos, then an EXIF-tagged copy")
    print("| vprflow's reader | photos | max | mean | equal bit for bit |")
    print("|---|---|---|---|---|")
    for label, exif, resize in (
        ("now: EXIF ignored, antialias, 224 x 224", "ignore", "antialias"),
        ("before: EXIF applied, linear (here at 224 x 224)", "apply", "linear"),
    ):
        for group in (photos, [turned]):
            worst, total, count, equal = 0.0, 0.0, 0, 0
            for path in group:
                theirs = _snsm_pixels(datasets_original, path)
                ours = _vprflow_pixels(path, exif, resize)
                diff = np.abs(ours.astype(np.float64) - theirs) * 255
                worst, total = max(worst, diff.max()), total + diff.sum()
                count, equal = count + diff.size, equal + int(np.array_equal(ours, theirs))
            which = "dataset" if group is photos else "EXIF 6"
            print(
                f"| {label} | {which} | {worst:.2f} | {total / count:.3f} | "
                f"{equal} / {len(group)} |"
            )


def _randomised_resnet(images: torch.Tensor, checks: Path):
    """torchvision's ResNet-50 with random weights, statistics drawn as
    check_trained_cnn.py draws them."""
    import torchvision

    sys.path.insert(0, str(checks))
    from check_trained_cnn import _randomise

    model = torchvision.models.resnet50(weights=None)
    return _randomise(model, images, seed=0).eval()


def compare_descriptors(datasets_original, vlad_module, script, photos: list[Path]) -> None:
    n = len(photos)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        listing = tmp / "images.txt"
        listing.write_text("\n".join(str(p) for p in photos) + "\n")
        config = {"global_params": {"threads": "0"}, "feature_extract": {"cacheBatchSize": "1"}}
        dataset = datasets_original.PlaceDataset(None, str(listing), "", None, config)
        batch = torch.stack([dataset[i][0] for i in range(min(n, 8))])
        source = _randomised_resnet(batch, Path(__file__).resolve().parent)
        checkpoint = tmp / "resnet50-0676ba61.pth"
        torch.save(source.state_dict(), checkpoint)
        theirs_model = script.ResNet50(pretrained=False)
        state = {k: v for k, v in source.state_dict().items() if not k.startswith("fc.")}
        theirs_model.model.load_state_dict(state)
        theirs_model.eval()
        opt = Namespace(
            result_save_folder=str(tmp / "out") + "/",
            emb_dim=SIZE // 16 * SIZE // 16 * 1024,
            nocuda=True,
            device=torch.device("cpu"),
            vlad_api=False,
            backbone="ResNet50",
            encoder=3,
            snsm=False,
            vlad=False,
            gem=False,
            gap=False,
            gmp=False,
        )
        theirs = script.feature_extraction(
            dataset, theirs_model, torch.device("cpu"), opt, config, None, None, None
        ).reshape(n, -1, 1024)
        entry = {"backbone": "resnet50", "checkpoint": str(checkpoint), "layer": 3}
        raw = load_model("features", {**entry, "normalize": False}, "cpu")
        old = load_model("features", entry, "cpu")
        now = np.stack(
            [raw.features(_vprflow_pixels(p, "ignore", "antialias")[None])[0] for p in photos]
        )
        before = np.stack(
            [old.features(_vprflow_pixels(p, "apply", "linear")[None])[0] for p in photos]
        )
    tokens = np.stack([normalize_tokens(g) for g in now]).reshape(n, -1, 1024)
    print(f"\nnormalised tokens, {n} images x {tokens.shape[1]} x 1024")
    print(
        f"max |SNSM's - vprflow's| = {np.abs(theirs - tokens).max():.2e} "
        f"(max |token value| {np.abs(theirs).max():.2e})"
    )

    references = len([p for p in photos if p.parent.name == photos[0].parent.name])
    centres = fit_spherical_kmeans(tokens[:references].reshape(-1, 1024), N_CLUSTERS)
    vlad = vlad_module.VLAD(num_clusters=N_CLUSTERS)
    import fast_pytorch_kmeans as fpk

    vlad.kmeans = fpk.KMeans(N_CLUSTERS, mode="cosine")
    vlad.c_centers = vlad.kmeans.centroids = torch.from_numpy(centres)
    vlad.desc_dim = 1024
    snsm = vlad.generate_multi(torch.from_numpy(theirs)).numpy()
    options = {"normalization": "channel", "normalize_descriptors": True}
    ours = np.stack([vlad_descriptor(g, options, centres=centres) for g in now])
    former = np.stack(
        [vlad_descriptor(g, {**options, "normalization": "none"}, centres=centres) for g in before]
    )
    print(f"\nVLAD, {n} images, K = {N_CLUSTERS}, the same centres on both sides")
    print("| vprflow | max abs diff | mean abs diff | same top-1 (queries) |")
    print("|---|---|---|---|")
    for label, vectors in (("now", ours), ("before (linear, per-patch L2 only)", former)):
        diff = np.abs(vectors - snsm)
        same = _same_top1(vectors, snsm, references)
        print(f"| {label} | {diff.max():.2e} | {diff.mean():.2e} | {same} |")


def _same_top1(ours: np.ndarray, theirs: np.ndarray, references: int) -> str:
    """How many queries get the same nearest reference (squared L2, as SNSM's faiss)."""

    def top1(v):
        d = ((v[references:, None, :] - v[None, :references, :]) ** 2).sum(-1)
        return d.argmin(1)

    same = int((top1(ours) == top1(theirs)).sum())
    return f"{same} / {len(ours) - references}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("snsm", type=Path, help="lfovia/SNSM's folder (holding SNSM/)")
    parser.add_argument("--data", type=Path, default=Path("../shared/data"))
    parser.add_argument("--pixels", nargs="+", default=["corridor", "roadscene"])
    parser.add_argument("--skip-pixels", action="store_true")
    parser.add_argument("--dataset", default="corridor", help="descriptors: <dataset>/{ref,query}")
    parser.add_argument(
        "--images", type=int, default=40, help="descriptors: the first N of each side"
    )
    args = parser.parse_args()
    stamp = args.snsm / "COMMIT"
    if stamp.is_file():
        print(stamp.read_text().strip())
    else:
        import subprocess

        head = subprocess.run(
            ["git", "-C", str(args.snsm), "rev-parse", "HEAD"], capture_output=True, text=True
        )
        print(f"lfovia/SNSM {head.stdout.strip() or '(commit unknown)'}")
    datasets_original, vlad_module, script = _snsm_modules(args.snsm)
    torch.set_grad_enabled(False)
    with tempfile.TemporaryDirectory() as tmp:
        photos = [] if args.skip_pixels else _photos(args.data, args.pixels)
        if photos:
            compare_pixels(datasets_original, photos, _exif_turned_copy(photos[0], Path(tmp)))
    folder = args.data / args.dataset
    pairs = [
        sorted(p for p in (folder / side).iterdir() if p.suffix.lower() in SUFFIXES)
        for side in ("ref", "query")
    ]
    first = [side[: args.images] for side in pairs]
    compare_descriptors(datasets_original, vlad_module, script, first[0] + first[1])


if __name__ == "__main__":
    main()
