"""Side by side: vprflow's trained VPR models against their original repositories.

For each model the original code is imported from ``ORIGINALS`` (a directory holding
the repositories' files, one folder per repository, e.g. extracted with ``git archive``;
an optional ``COMMIT`` file in each folder names the repository and commit), given
identical random weights (drawn once for the original model, saved in its own state-dict
layout with ``torch.save`` / safetensors, then read by vprflow's loader), and both are run
on the same random ImageNet-normalised batch. Printed: the model, the original's
repository and commit, max |difference| of the descriptors, the descriptor length, the
input size and the checkpoint layout the loader read.

Folders used: ``pytorch-NetVlad`` (netvlad.py), ``Patch-NetVLAD``
(patchnetvlad/models), ``salad`` (models/backbones/dinov2.py,
models/aggregators/salad.py), ``Bag-of-Queries`` (src/backbones.py, src/boq.py),
``MegaLoc`` (megaloc_model.py), ``VLAD-BuFF`` (the folder of AnyLoc/Revisit-Anything:
hubconf.py, vpr_model.py, models/; its ``VPRModel`` is built as ``hubconf.vlad_buff``
builds it, with stand-ins for the training-only pytorch_lightning, wandb, utils and
sklearn) and ``dinov2`` (facebookresearch/dinov2, the backbone SALAD, BoQ and VLAD-BuFF
load through torch.hub; here ``torch.hub.load`` is pointed at it with
``pretrained=False``). torchvision must be importable (for VGG16 and the originals),
e.g. ``PYTHONPATH=/tmp/tv`` after ``bash ../shared/tools/torchvision-for-checks.sh /tmp/tv``.

    PYTHONPATH=/tmp/tv python benchmarks/check_trained_vit.py /tmp/originals

Runs on CPU in float32; ``--vit-depth`` reduces the ViT-B/14 depth (default all 12
blocks), ``--netvlad-size`` the NetVLAD input (default 480 x 640). VLAD-BuFF's published
whitening (8192 x 49152) makes its check hold about 8 GB at once.
"""

from __future__ import annotations

import argparse
import configparser
import importlib.machinery
import importlib.util
import math
import sys
import tempfile
import types
from pathlib import Path

import numpy as np
import torch
from originals import commit_of, load_module

from vprflow.models.kinds import IMAGENET_MEAN, IMAGENET_STD
from vprflow.models.trained.boq_dinov2 import load_boq_dinov2
from vprflow.models.trained.megaloc import load_megaloc
from vprflow.models.trained.netvlad import load_netvlad
from vprflow.models.trained.salad import load_salad
from vprflow.models.trained.vlad_buff import load_vlad_buff
from vprflow.models.trunks.dinov2 import dinov2_config
from vprflow.models.trunks.vgg import load_vgg16_trunk


def _randomise(model: torch.nn.Module, seed: int) -> torch.nn.Module:
    """Every parameter re-drawn: weights He-scaled by fan-in, biases small, norms and
    layer scales near 1, tokens / queries O(1), so no block is a near-identity (MegaLoc
    initialises its LayerScales at 1e-5 and its tokens at 0)."""
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, parameter in model.named_parameters():
            noise = torch.randn(parameter.shape, generator=generator)
            leaf = name.rpartition(".")[2]
            if parameter.ndim == 0 or leaf in ("gamma", "lambda1"):
                value = 1.0 + 0.2 * noise
            elif "norm" in name and leaf in ("weight", "bias"):
                value = (1.0 if leaf == "weight" else 0.0) + 0.1 * noise
            elif leaf.endswith("bias") and parameter.ndim == 1:
                value = 0.05 * noise
            elif leaf in ("cls_token", "pos_embed", "mask_token", "queries", "centroids"):
                value = 0.5 * noise
            else:
                fan_in = parameter[0].numel() if parameter.ndim > 1 else parameter.numel()
                value = noise * math.sqrt(2.0 / fan_in)
            parameter.copy_(value)
    return model.eval()


def _images(count: int, height: int, width: int, seed: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(seed)
    pixels = torch.rand(count, 3, height, width, generator=generator)
    mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    return (pixels - mean) / std


def _stub_sklearn() -> None:
    # The originals import NearestNeighbors for k-means initialisation only.
    try:
        import sklearn.neighbors  # noqa: F401
    except ImportError:
        sklearn = types.ModuleType("sklearn")
        neighbors = types.ModuleType("sklearn.neighbors")
        neighbors.NearestNeighbors = None
        # torch._dynamo (imported by torchvision) looks modules up by their spec.
        for stub in (sklearn, neighbors):
            stub.__spec__ = importlib.machinery.ModuleSpec(stub.__name__, None)
        sklearn.neighbors = neighbors
        sys.modules.update({"sklearn": sklearn, "sklearn.neighbors": neighbors})
    try:
        import faiss  # noqa: F401
    except ImportError:
        faiss = types.ModuleType("faiss")
        faiss.__spec__ = importlib.machinery.ModuleSpec("faiss", None)
        sys.modules["faiss"] = faiss


def _hub_dinov2(originals: Path, depth: int):
    """``torch.hub.load('facebookresearch/dinov2', 'dinov2_vitb14')`` without weights."""
    sys.path.insert(0, str(originals / "dinov2"))
    from dinov2.hub.backbones import dinov2_vitb14

    def load(repo, name, *args, **kwargs):
        if (repo, name) != ("facebookresearch/dinov2", "dinov2_vitb14"):
            raise ValueError(f"unexpected torch.hub.load({repo!r}, {name!r})")
        model = dinov2_vitb14(pretrained=False)
        model.blocks = model.blocks[:depth]
        return model

    return load


def _difference(ours: torch.Tensor, theirs: torch.Tensor) -> float:
    if ours.shape != theirs.shape:
        raise AssertionError(
            f"shapes differ: ours {tuple(ours.shape)}, original {tuple(theirs.shape)}"
        )
    return float((ours - theirs).abs().max())


def check_vgg(originals: Path, size: tuple[int, int], work: Path) -> dict:
    import torchvision

    original = _randomise(torchvision.models.vgg16(weights=None), 1)
    path = work / "vgg16.pth"
    torch.save(original.state_dict(), path)
    ours = load_vgg16_trunk(str(path))
    images = _images(2, *size, seed=2)
    with torch.no_grad():
        theirs = original.features[:29](images)
        mine = ours(images)
    return {
        "model": "VGG16 trunk (conv5_3)",
        "source": f"torchvision {torchvision.__version__}",
        "diff": _difference(mine, theirs),
        "scale": float(theirs.abs().max()),
        "dim": f"512 x {mine.shape[2]} x {mine.shape[3]}",
        "input": size,
        "layout": "torchvision vgg16 state dict (features.*, classifier.*)",
    }


def _netvlad_encoder():
    import torchvision

    return torch.nn.Sequential(
        *list(torchvision.models.vgg16(weights=None).features.children())[:-2]
    )


def check_nanne(originals: Path, size: tuple[int, int], work: Path) -> dict:
    _stub_sklearn()
    folder = originals / "pytorch-NetVlad"
    netvlad = load_module(folder / "netvlad.py", "nanne_netvlad")
    original = torch.nn.Module()
    original.add_module("encoder", _netvlad_encoder())
    original.add_module("pool", netvlad.NetVLAD(num_clusters=64, dim=512, vladv2=False))
    _randomise(original, 3)
    with torch.no_grad():
        original.pool.conv.weight.mul_(20.0)  # sharp soft-assignment, as trained ones are
    path = work / "checkpoint.pth.tar"
    torch.save(
        {"epoch": 30, "state_dict": original.state_dict(), "best_score": np.float64(0.9)}, path
    )
    ours = load_netvlad(str(path), "nanne-pitts30k")
    images = _images(2, *size, seed=4)
    with torch.no_grad():
        theirs = original.pool(original.encoder(images))
        mine = ours(images)
    return {
        "model": "NetVLAD nanne-pitts30k",
        "source": commit_of(folder),
        "diff": _difference(mine, theirs),
        "scale": float(theirs.abs().max()),
        "dim": mine.shape[1],
        "input": size,
        "layout": "{epoch, state_dict: encoder.*, pool.centroids, pool.conv.weight, best_score}",
    }


def check_patchnetvlad(originals: Path, size: tuple[int, int], work: Path, pcs: int) -> list:
    _stub_sklearn()
    folder = originals / "Patch-NetVLAD"
    # The package's __init__ imports its dataset tools; only the models are needed.
    for package in ("patchnetvlad", "patchnetvlad.models"):
        module = types.ModuleType(package)
        module.__path__ = [str(folder.joinpath(*package.split(".")))]
        sys.modules[package] = module
    from patchnetvlad.models.models_generic import get_model, get_pca_encoding

    config = configparser.ConfigParser()
    config["global_params"] = {"pooling": "netvlad", "num_clusters": "64", "vladv2": "False"}
    config["global_params"]["num_pcs"] = str(pcs)
    original = get_model(_netvlad_encoder(), 512, config["global_params"], append_pca_layer=True)
    _randomise(original, 5)
    with torch.no_grad():
        original.pool.conv.weight.mul_(20.0)
        original.WPCA[0].weight.mul_(0.3)
    path = work / f"pitts_WPCA{pcs}.pth.tar"
    torch.save({"epoch": 1, "state_dict": original.state_dict()}, path)
    images = _images(2, *size, seed=6)
    with torch.no_grad():
        vlad = original.pool(original.encoder(images))
        whitened = get_pca_encoding(original, vlad)
    rows = []
    for variant, theirs in (
        (f"patchnetvlad-pitts30k-{pcs}", whitened),
        ("patchnetvlad-pitts30k-32768", vlad),
    ):
        ours = load_netvlad(str(path), variant)
        with torch.no_grad():
            mine = ours(images)
        rows.append(
            {
                "model": f"NetVLAD {variant}",
                "source": commit_of(folder),
                "diff": _difference(mine, theirs),
                "scale": float(theirs.abs().max()),
                "dim": mine.shape[1],
                "input": size,
                "layout": f"{{epoch, state_dict: encoder.*, pool.*, WPCA.0.*}} ({path.name})",
            }
        )
    return rows


def check_salad(originals: Path, depth: int, work: Path) -> dict:
    folder = originals / "salad"
    backbones = load_module(folder / "models/backbones/dinov2.py", "salad_dinov2")
    aggregators = load_module(folder / "models/aggregators/salad.py", "salad_salad")
    hub_load, torch.hub.load = torch.hub.load, _hub_dinov2(originals, depth)
    try:
        original = torch.nn.Module()
        original.add_module(
            "backbone",
            backbones.DINOv2(
                "dinov2_vitb14", num_trainable_blocks=4, norm_layer=True, return_token=True
            ),
        )
    finally:
        torch.hub.load = hub_load
    original.add_module(
        "aggregator",
        aggregators.SALAD(num_channels=768, num_clusters=64, cluster_dim=128, token_dim=256),
    )
    _randomise(original, 7)
    path = work / "dino_salad.ckpt"
    torch.save(original.state_dict(), path)
    ours = load_salad(str(path), dinov2_config(num_hidden_layers=depth))
    images = _images(2, 322, 322, seed=8)
    with torch.no_grad():
        theirs = original.aggregator(original.backbone(images))
        mine = ours(images)
    return {
        "model": f"SALAD (ViT-B/14, {depth} blocks)",
        "source": f"{commit_of(folder)}; {commit_of(originals / 'dinov2')}",
        "diff": _difference(mine, theirs),
        "scale": float(theirs.abs().max()),
        "dim": mine.shape[1],
        "input": (322, 322),
        "layout": "state dict: backbone.model.<hub DINOv2>, aggregator.*",
    }


def check_boq(originals: Path, depth: int, work: Path) -> dict:
    folder = originals / "Bag-of-Queries"
    hub_load, torch.hub.load = torch.hub.load, _hub_dinov2(originals, depth)
    try:
        backbones = load_module(folder / "src/backbones.py", "boq_backbones")
        boq = load_module(folder / "src/boq.py", "boq_boq")
        backbone = backbones.DinoV2()
    finally:
        torch.hub.load = hub_load
    original = torch.nn.Module()
    original.add_module("backbone", backbone)
    original.add_module(
        "aggregator",
        boq.BoQ(in_channels=768, proj_channels=384, num_queries=64, num_layers=2, row_dim=32),
    )
    _randomise(original, 9)
    path = work / "dinov2_12288.pth"
    torch.save(original.state_dict(), path)
    ours = load_boq_dinov2(str(path), dinov2_config(num_hidden_layers=depth))
    images = _images(2, 322, 322, seed=10)
    with torch.no_grad():
        theirs = original.aggregator(original.backbone(images))[0]
        mine = ours(images)
    return {
        "model": f"BoQ-DINOv2 (ViT-B/14, {depth} blocks)",
        "source": f"{commit_of(folder)}; {commit_of(originals / 'dinov2')}",
        "diff": _difference(mine, theirs),
        "scale": float(theirs.abs().max()),
        "dim": mine.shape[1],
        "input": (322, 322),
        "layout": "state dict: backbone.dino.<hub DINOv2>, aggregator.*",
    }


def check_megaloc(originals: Path, depth: int, work: Path) -> list:
    from safetensors.torch import save_file

    folder = originals / "MegaLoc"
    megaloc = load_module(folder / "megaloc_model.py", "megaloc_original")
    original = megaloc.MegaLoc()
    original.backbone.blocks = original.backbone.blocks[:depth]
    _randomise(original, 11)
    path = work / "model.safetensors"
    save_file({k: v.contiguous() for k, v in original.state_dict().items()}, str(path))
    ours = load_megaloc(str(path), dinov2_config(num_hidden_layers=depth))
    rows = []
    for size in ((322, 322), (300, 400)):
        images = _images(2, *size, seed=12)
        with torch.no_grad():
            theirs = original(images)
            mine = ours(images)
        rows.append(
            {
                "model": f"MegaLoc (ViT-B/14, {depth} blocks)",
                "source": commit_of(folder),
                "diff": _difference(mine, theirs),
                "scale": float(theirs.abs().max()),
                "dim": mine.shape[1],
                "input": size,
                "layout": "safetensors: backbone.<hub DINOv2>, aggregator.{agg.*, linear.*}",
            }
        )
    return rows


def _hub_function(folder: Path, name: str, namespace: dict):
    """The function ``name`` of VLAD-BuFF's hubconf.py, run as written with the file's
    constants and functions (its imports pull in the training stack)."""
    import ast

    source = (folder / "hubconf.py").read_text()
    body = [n for n in ast.parse(source).body if isinstance(n, (ast.Assign, ast.FunctionDef))]
    exec(compile(ast.Module(body, []), str(folder / "hubconf.py"), "exec"), namespace)
    return namespace[name]


def _vlad_buff_original(folder: Path, originals: Path, depth: int, nv_pca, num_pcs):
    """``VPRModel`` as ``hubconf.vlad_buff(antiburst=True, nv_pca, wpca=True, num_pcs)``
    builds it, its arguments from hubconf's own ``parse_args``."""
    import argparse

    _stub_sklearn()
    try:
        import sklearn.decomposition  # noqa: F401
    except ImportError:
        decomposition = types.ModuleType("sklearn.decomposition")
        decomposition.__spec__ = importlib.machinery.ModuleSpec(decomposition.__name__, None)
        decomposition.PCA = None  # the NetVLAD initialisation's only
        sys.modules["sklearn.decomposition"] = decomposition
    # Training-only imports of vpr_model.py: its module is a LightningModule with a loss.
    lightning = types.ModuleType("pytorch_lightning")

    class LightningModule(torch.nn.Module):
        def save_hyperparameters(self, *args, **kwargs):
            pass

    lightning.LightningModule = LightningModule
    utils = types.ModuleType("utils")
    utils.get_loss = utils.get_miner = lambda *args: None
    for stub in (lightning, utils, types.ModuleType("wandb")):
        stub.__spec__ = importlib.machinery.ModuleSpec(stub.__name__, None)
        sys.modules[stub.__name__] = stub
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))
    import vpr_model

    parse_args = _hub_function(folder, "parse_args", {"argparse": argparse})
    argv, sys.argv = sys.argv, ["hubconf.py"]
    try:
        args = parse_args(antiburst=True, nv_pca=nv_pca, wpca=True, num_pcs=num_pcs)
    finally:
        sys.argv = argv
    hub_load, torch.hub.load = torch.hub.load, _hub_dinov2(originals, depth)
    try:
        return vpr_model.VPRModel(
            backbone_arch=args.backbone,
            backbone_config={
                "num_trainable_blocks": args.num_trainable_blocks,
                "return_token": False,
                "norm_layer": args.norm_layer,
            },
            agg_arch=args.aggregation,
            agg_config=args,
            args=args,
        ).eval()
    finally:
        torch.hub.load = hub_load


def check_vlad_buff(originals: Path, depth: int, work: Path) -> list:
    """Both published VLAD-BuFF models: the original with random weights, saved as
    ``add_pca.py`` saves it (``{num_pcs, state_dict}``, the whitening as ``WPCA_<n>`` in
    float64), read back once by hubconf's own key handling into a second original (which
    must equal the first exactly) and once by vprflow's loader; the whitened descriptor
    (``eval.py``: ``model.WPCA`` of ``model(images)``) and the VLAD before it."""
    folder = originals / "VLAD-BuFF"
    rows = []
    for seed, (nv_pca, num_pcs) in enumerate(((None, 8192), (192, 4096)), start=13):
        original = _vlad_buff_original(folder, originals, depth, nv_pca, num_pcs)
        _randomise(original, seed)
        with torch.no_grad():
            # Trained-like: a sharp soft assignment, unit centroids, AntiBurst near its
            # initial (8, 7, 1).
            original.aggregator.conv.weight.mul_(20.0)
            centroids = original.aggregator.centroids
            centroids.copy_(torch.nn.functional.normalize(centroids, dim=1))
            noise = torch.randn(3, generator=torch.Generator().manual_seed(seed))
            original.aggregator.ab_params.copy_(torch.tensor([8.0, 7.0, 1.0]) + 0.1 * noise)
        images = _images(2, 322, 322, seed=seed)
        with torch.no_grad():
            vlad = original(images)
            whitened = original.WPCA(vlad.unsqueeze(-1).unsqueeze(-1))
        state = {
            (f"WPCA_{num_pcs}." + k[len("WPCA.") :] if k.startswith("WPCA.") else k): (
                v.double() if k.startswith("WPCA.") else v
            )
            for k, v in original.state_dict().items()
        }
        name = "dnv2_NV_{}AB_wpca{}_last.ckpt".format(f"{nv_pca}PCA_" if nv_pca else "", num_pcs)
        path = work / name
        torch.save({"num_pcs": num_pcs, "state_dict": state}, path)
        del original, state
        # hubconf.vlad_buff's loading, on a fresh original.
        replace_key = _hub_function(folder, "replace_key", {})
        again = _vlad_buff_original(folder, originals, depth, nv_pca, num_pcs)
        checkpoint = torch.load(path, weights_only=True)
        renamed = {replace_key(k, num_pcs): v for k, v in checkpoint["state_dict"].items()}
        own = again.state_dict()
        again.load_state_dict({k: v for k, v in renamed.items() if k in own})
        del checkpoint, renamed, own
        with torch.no_grad():
            vlad_again = again(images)
            if not torch.equal(again.WPCA(vlad_again[..., None, None]), whitened):
                raise AssertionError(f"{name}: hubconf's loading changed the original's output")
        del again
        config = dinov2_config(num_hidden_layers=depth)
        for pcs, theirs in ((num_pcs, whitened), (None, vlad)):
            ours = load_vlad_buff(str(path), config, nv_pca=nv_pca, num_pcs=pcs)
            with torch.no_grad():
                mine = ours(images)
            del ours
            variant = (
                f"whitened to {num_pcs}" if pcs else f"VLAD {vlad.shape[1]}, before the whitening"
            )
            rows.append(
                {
                    "model": f"VLAD-BuFF {name.rsplit('_wpca', 1)[0]} {variant} "
                    f"(ViT-B/14, {depth} blocks)",
                    "source": f"{commit_of(folder)}; {commit_of(originals / 'dinov2')}",
                    "diff": _difference(mine, theirs),
                    "scale": float(theirs.abs().max()),
                    "dim": mine.shape[1],
                    "input": (322, 322),
                    "layout": f"{{num_pcs, state_dict: backbone.model.<hub DINOv2>, "
                    f"aggregator.*, WPCA_{num_pcs}.0.* (float64)}} ({name})",
                }
            )
        path.unlink()
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("originals", type=Path, help="folder of the original repositories")
    parser.add_argument("--vit-depth", type=int, default=12, help="ViT-B/14 blocks (12)")
    parser.add_argument("--netvlad-size", type=int, nargs=2, default=(480, 640), metavar=("H", "W"))
    parser.add_argument("--pcs", type=int, default=4096, help="Patch-NetVLAD whitening dims")
    parser.add_argument(
        "--only",
        nargs="*",
        default=("vgg", "nanne", "patchnetvlad", "salad", "boq", "megaloc", "vlad_buff"),
    )
    args = parser.parse_args(argv)
    torch.set_grad_enabled(False)
    size = tuple(args.netvlad_size)
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        work = Path(scratch)
        checks = {
            "vgg": lambda: [check_vgg(args.originals, size, work)],
            "nanne": lambda: [check_nanne(args.originals, size, work)],
            "patchnetvlad": lambda: check_patchnetvlad(args.originals, size, work, args.pcs),
            "salad": lambda: [check_salad(args.originals, args.vit_depth, work)],
            "boq": lambda: [check_boq(args.originals, args.vit_depth, work)],
            "megaloc": lambda: check_megaloc(args.originals, args.vit_depth, work),
            "vlad_buff": lambda: check_vlad_buff(args.originals, args.vit_depth, work),
        }
        for name in args.only:
            for row in checks[name]():
                rows.append(row)
                print(f"# {row['model']}: max |diff| {row['diff']:.3g}", file=sys.stderr)
    header = ("model", "source (repository commit)", "max abs diff", "max abs entry")
    header += ("dim", "input HxW", "checkpoint layout")
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for row in rows:
        height, width = row["input"]
        cells = (row["model"], row["source"], f"{row['diff']:.2e}", f"{row['scale']:.2e}")
        cells += (str(row["dim"]), f"{height}x{width}", row["layout"])
        print("| " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
