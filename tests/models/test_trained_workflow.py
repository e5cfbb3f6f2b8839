"""The trained VPR models as workflow components: tiny random models saved in
each published checkpoint layout (NetVLAD's Patch-NetVLAD ``state_dict``, SALAD's
``dino_salad.ckpt``, BoQ-DINOv2's ``dinov2_12288.pth``, MegaLoc's ``model.safetensors``),
loaded through the real loaders by the features stage, run through the descriptors,
recall and re-rank stages with the rules' own runners, and their plans.

The published loaders build the published sizes; the tests give them the tiny sizes the
models' own tests use (their ``config`` / ``encoder`` / size arguments) by wrapping the
loader models/loaders.py names, which imports its module when a job runs."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import torch
from synthetic import make_dataset
from trained_references import prefixed, randomise, tiny_config
from workflow_helpers import run_stage as run_planned_stage
from workflow_helpers import toy_config

from vprflow.core import stores
from vprflow.core.errors import PlanError
from vprflow.data.images import read_image, resize_image
from vprflow.models import kinds
from vprflow.models.checkpoints import CheckpointError
from vprflow.models.kinds import IMAGENET_MEAN, IMAGENET_STD
from vprflow.models.trained import boq_dinov2, megaloc, netvlad, salad, vlad_buff
from vprflow.models.trunks.dinov2 import dinov2_hub_state_dict
from vprflow.planning.config import validate_config
from vprflow.planning.plan import build_plan
from vprflow.stages.readers import Dataset

REPO = Path(__file__).resolve().parents[2]
SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"
# A float32 forward on the same pixels, in another process order: descriptors are unit
# vectors of O(0.1) entries.
FLOAT32_ATOL = 1e-5


def _netvlad_encoder() -> torch.nn.Sequential:
    # Stride 16, as VGG16 conv5_3: the adapter's patch size holds for the dense map.
    return torch.nn.Sequential(torch.nn.Conv2d(3, 8, kernel_size=16, stride=16))


# Per trained kind: the module, its loader's name, the tiny sizes its loader is given,
# how to build the tiny model, the checkpoint's file name and its state dict.
TINY = {
    "netvlad": (
        netvlad,
        "load_netvlad",
        lambda: {"encoder": _netvlad_encoder()},
        lambda: netvlad.NetVLADModel(4, 6, encoder=_netvlad_encoder(), encoder_dim=8),
        "pitts_WPCA4096.pth.tar",
        lambda model: {"epoch": 3, "state_dict": model.state_dict()},
    ),
    "salad": (
        salad,
        "load_salad",
        lambda: {"config": tiny_config(), "num_clusters": 4, "cluster_dim": 8},
        lambda: salad.SALAD(tiny_config(), num_clusters=4, cluster_dim=8),
        "dino_salad.ckpt",
        lambda model: {
            **prefixed(dinov2_hub_state_dict(model.backbone), "backbone.model."),
            **prefixed(model.aggregator.state_dict(), "aggregator."),
        },
    ),
    "boq_dinov2": (
        boq_dinov2,
        "load_boq_dinov2",
        lambda: {"config": tiny_config(), **BOQ_SIZES},
        lambda: boq_dinov2.BoQDinoV2(tiny_config(), **BOQ_SIZES),
        "dinov2_12288.pth",
        lambda model: {
            **prefixed(dinov2_hub_state_dict(model.backbone), "backbone.dino."),
            **prefixed(model.aggregator.state_dict(), "aggregator."),
        },
    ),
    # The published default: no pre-pool PCA, whitened to 8192 (from a 4 x 32 VLAD here).
    "vlad_buff": (
        vlad_buff,
        "load_vlad_buff",
        lambda: {"config": tiny_config(), "num_clusters": 4},
        lambda: vlad_buff.VladBuff(tiny_config(), num_clusters=4),
        "dnv2_NV_AB_wpca8192_last.ckpt",
        lambda model: {
            "num_pcs": 8192,
            "state_dict": {
                **prefixed(dinov2_hub_state_dict(model.backbone), "backbone.model."),
                **prefixed(model.aggregator.state_dict(), "aggregator."),
                **prefixed(model.WPCA.state_dict(), "WPCA_8192."),
            },
        },
    ),
    "megaloc": (
        megaloc,
        "load_megaloc",
        lambda: {"config": tiny_config(), **MEGALOC_SIZES},
        lambda: megaloc.MegaLoc(tiny_config(), **MEGALOC_SIZES),
        "model.safetensors",
        lambda model: {
            **prefixed(
                {
                    k: v
                    for k, v in dinov2_hub_state_dict(model.backbone).items()
                    if k != "mask_token"  # MegaLoc's file has none
                },
                "backbone.",
            ),
            **prefixed(model.aggregator.state_dict(), "aggregator."),
        },
    ),
}
BOQ_SIZES = {"proj_channels": 128, "num_queries": 4, "num_layers": 2, "row_dim": 3}
MEGALOC_SIZES = {
    "feat_dim": 24,
    "num_clusters": 4,
    "cluster_dim": 8,
    "token_dim": 16,
    "mlp_dim": 20,
}


def save_tiny(kind: str, folder: Path, seed: int = 1) -> tuple[torch.nn.Module, Path]:
    """A tiny random ``kind`` model and its checkpoint in the published layout."""
    _, _, _, build, file, state = TINY[kind]
    model = randomise(build(), seed)
    path = folder / kind / file
    path.parent.mkdir(parents=True, exist_ok=True)
    if file.endswith(".safetensors"):
        from safetensors.torch import save_file

        save_file({k: v.contiguous() for k, v in state(model).items()}, str(path))
    else:
        torch.save(state(model), path)
    return model.eval(), path


@pytest.fixture
def tiny_loaders(monkeypatch):
    """The models' loaders, given the tiny sizes (the real loaders read the files)."""
    for module, name, sizes, *_ in TINY.values():
        original = getattr(module, name)

        def tiny(path, *args, _original=original, _sizes=sizes, **options):
            return _original(path, *args, **options, **_sizes())

        monkeypatch.setattr(module, name, tiny)


def run_stage(plan, stage: str, key: str, data_root: Path, out: Path, done: dict) -> str:
    """:func:`workflow_helpers.run_stage` in batches of 3 (the models' batching runs)."""
    return run_planned_stage(
        plan, stage, key, data_root, out, done, run={"device": "cpu", "batch_size": 3}
    )


def trained_config(root: Path, checkpoints: dict[str, Path], methods: dict, **dataset) -> dict:
    make_dataset(root / "data" / "toy", n_places=4, width=64, height=48)
    config = toy_config(root / "data", resolution=[64, 48], methods=list(methods), **dataset)
    for kind, path in checkpoints.items():
        config["backbones"][kind] = {"backbone": kind, "checkpoint": str(path)}
    config["methods"] = methods
    config["vocabulary"].update(n_clusters=3, n_iter=5)
    return config


def model_pixels(path: str, width: int, height: int, method: str = "antialias") -> np.ndarray:
    """What the published readers give the model: PIL's pixels (EXIF ignored), resized
    to the model's input size by its reader's ``method`` (PIL bilinear for most; BoQ's
    bicubic on the float tensor)."""
    return resize_image(read_image(path, "ignore"), width, height, method)


def imagenet(pixels: np.ndarray, model) -> torch.Tensor:
    x = torch.from_numpy(pixels).permute(2, 0, 1)[None].float()
    mean, std = torch.tensor(model.mean)[:, None, None], torch.tensor(model.std)[:, None, None]
    return (x - mean) / std


def test_every_trained_kind_is_a_global_method_whose_descriptor_is_the_models(
    tmp_path, tiny_loaders
):
    """Each trained kind as a method with aggregator ``model``: the descriptors store
    holds, per image, the model's own forward on the image the published reader gives it
    (PIL pixels resized to the kind's published input size, ImageNet-normalised), and
    recall (with precision-recall) and re-ranking run on it as on any global method."""
    sources, checkpoints = {}, {}
    for seed, kind in enumerate(TINY, start=1):
        sources[kind], checkpoints[kind] = save_tiny(kind, tmp_path / "weights", seed)
    methods = {f"{kind}_own": {"aggregator": "model", "features": kind} for kind in TINY}
    config = trained_config(
        tmp_path,
        checkpoints,
        methods,
        rerank={"netvlad_own": ["mnn"]},
        recall_at=[1, 2],
    )
    config["rerankers"] = {"mnn": {"kind": "mnn", "features": "daisy", "top_k": 3}}
    plan = build_plan(validate_config(config, SCHEMA))
    rows = {run.method: run for run in plan.runs["toy"]}
    root = tmp_path / "data"
    assert sorted(rows) == sorted([*methods, "netvlad_own+mnn"])
    done: dict = {}
    for kind, model in sources.items():
        run = rows[f"{kind}_own"]
        assert run.row_params["aggregator"] == "model"
        assert run.row_params["features.backbone"] == kind
        assert run.row_params["features.output"] == "descriptor"
        # The published input size, or the images' own (MegaLoc; here all 64 x 48).
        spec = kinds.BACKBONES[kind].spec
        width, height = spec.input_size or (64, 48)
        assert run.row_params["features.resolution"] == (
            "own" if kind == "megaloc" else f"{width} {height}"
        )
        recall = plan.get("recall", run.recall_key)
        recall_path = run_stage(
            plan, "recall", run.recall_key, tmp_path / "data", tmp_path / "c", done
        )
        descriptors = stores.open_store(done["descriptors", recall.inputs["descriptors"][1]])
        dataset = Dataset(done["images", plan.images_keys["toy"]])
        stored = np.asarray(descriptors["descriptors"][...])
        with torch.no_grad():
            expected = np.concatenate(
                [
                    model(
                        imagenet(model_pixels(root / p, width, height, spec.resize), model)
                    ).numpy()
                    for p in dataset.paths
                ]
            )
        assert stored.shape == (dataset.n_images, model.dim), kind
        np.testing.assert_allclose(stored, expected, rtol=0, atol=FLOAT32_ATOL, err_msg=kind)
        np.testing.assert_allclose(np.linalg.norm(stored, axis=1), 1.0, atol=1e-6)
        result = stores.open_store(recall_path)
        assert set(result.attrs["recall"]) == {"1", "2"}
        assert result.attrs["precision_recall"] is not None
        assert result.attrs["descriptor_dim"] == model.dim
    reranked = rows["netvlad_own+mnn"]
    run_stage(plan, "recall", reranked.recall_key, tmp_path / "data", tmp_path / "c", done)
    assert any(stage == "rerank" for stage, _ in done)


@pytest.mark.parametrize("kind", ["netvlad", "salad"])
def test_output_features_is_the_map_the_head_reads_and_feeds_anyloc_vlad(
    kind, tmp_path, tiny_loaders
):
    """``output: features`` stores the dense map the model's head reads (NetVLAD's
    conv5_3 stand-in, SALAD's normed DINOv2 tokens), per-patch L2-normalised as every
    backbone's, with the map's stride as patch size; AnyLoc-VLAD runs over it."""
    model, checkpoint = save_tiny(kind, tmp_path / "weights")
    config = trained_config(
        tmp_path, {kind: checkpoint}, {"vlad": {"aggregator": "anyloc_vlad", "features": kind}}
    )
    config["backbones"][kind]["output"] = "features"
    plan = build_plan(validate_config(config, SCHEMA))
    (run,) = plan.runs["toy"]
    done: dict = {}
    run_stage(plan, "recall", run.recall_key, tmp_path / "data", tmp_path / "c", done)
    (features_key,) = plan.stages["features"]
    features = stores.open_store(done["features", features_key])
    spec = kinds.BACKBONES[kind].spec
    width, height = spec.input_size
    assert features.attrs["patch_size"] == spec.patch_size
    dataset = Dataset(done["images", plan.images_keys["toy"]])
    # AnyLoc's reader (OpenCV: linear, EXIF applied) for the dense features.
    image = read_image(tmp_path / "data" / dataset.paths[0], "apply")
    pixels = resize_image(image, width, height, "linear")
    with torch.no_grad():
        expected = model.feature_map(imagenet(pixels, model))[0].permute(1, 2, 0).numpy()
    expected = expected / np.linalg.norm(expected, axis=-1, keepdims=True)
    stored = np.asarray(features["features"][0])
    assert stored.shape == (height // spec.patch_size, width // spec.patch_size, expected.shape[-1])
    np.testing.assert_allclose(stored, expected, rtol=0, atol=FLOAT32_ATOL)
    assert (tmp_path / "c" / "vocabulary").is_dir()


# Images of other sizes than the dataset's 64 x 48 (width, height): sides off the
# 14-pixel grid (MegaLoc resizes them itself), a run of two equal sizes to batch together.
MIXED_SIZES = {"ref/0001.png": (70, 50), "ref/0002.png": (57, 43), "ref/0003.png": (57, 43)}


def mixed_size_config(root: Path, checkpoints: dict[str, Path], methods: dict) -> dict:
    """:func:`trained_config`'s toy dataset with :data:`MIXED_SIZES` replacing some of
    its images."""
    from PIL import Image
    from synthetic import place_image

    config = trained_config(root, checkpoints, methods)
    rng = np.random.default_rng(5)
    for name, (width, height) in MIXED_SIZES.items():
        pixels = (place_image(rng, width, height) * 255).astype(np.uint8)
        Image.fromarray(pixels).save(root / "data" / "toy" / name)
    return config


def test_megaloc_and_cosplace_read_each_image_at_its_own_size_as_their_evaluations_do(
    tmp_path, tiny_loaders
):
    """``resolution: own`` (MegaLoc's, CosPlace's and EigenPlaces' default): each image's
    stored descriptor is the model's forward on that image alone, unresized (PIL's pixels,
    ImageNet-normalised), on a dataset of mixed sizes; images of one size share a batch
    (the stage runs batches of 3 here)."""
    from vprflow.models.trained import cosplace

    megaloc_model, megaloc_file = save_tiny("megaloc", tmp_path / "weights")
    torch.manual_seed(0)
    cosplace_model = cosplace.GeoLocalizationNet("ResNet18", 32).eval()
    cosplace_file = tmp_path / "weights" / "ResNet18_32_cosplace.pth"
    torch.save(cosplace_model.state_dict(), cosplace_file)
    models = {"megaloc": megaloc_model, "cosplace": cosplace_model}
    methods = {kind: {"aggregator": "model", "features": kind} for kind in models}
    config = mixed_size_config(
        tmp_path, {"megaloc": megaloc_file, "cosplace": cosplace_file}, methods
    )
    config["backbones"]["cosplace"]["variant"] = "ResNet18_32"
    plan = _plan(config)
    done: dict = {}
    for run in plan.runs["toy"]:
        model = models[run.method]
        assert run.row_params["features.resolution"] == "own"
        key = plan.get("recall", run.recall_key).inputs["descriptors"][1]
        run_stage(plan, "descriptors", key, tmp_path / "data", tmp_path / "c", done)
        descriptors = stores.open_store(done["descriptors", key])
        dataset = Dataset(done["images", plan.images_keys["toy"]])
        stored = np.asarray(descriptors["descriptors"][...])
        for index, path in enumerate(dataset.paths):
            pixels = read_image(tmp_path / "data" / path, "ignore")
            with torch.no_grad():
                alone = model(imagenet(pixels, model))[0].numpy()
            np.testing.assert_allclose(
                stored[index], alone, rtol=0, atol=FLOAT32_ATOL, err_msg=f"{run.method} {path}"
            )
        features_key = plan.get("descriptors", key).inputs["features"][1]
        # Sizes differ: no one image size to state.
        assert stores.open_store(done["features", features_key]).attrs["image_size"] is None


def test_a_dense_map_at_each_images_own_size_is_refused_naming_the_image_and_its_size(
    tmp_path, tiny_loaders
):
    """The stages after a dense map stack it: under ``resolution: own`` an image whose
    size differs from the first's is refused before any is computed, naming both files,
    their sizes and the key; at the dataset's resolution the same entry runs."""
    _, checkpoint = save_tiny("megaloc", tmp_path / "weights")
    methods = {"vlad": {"aggregator": "anyloc_vlad", "features": "megaloc"}}
    config = mixed_size_config(tmp_path, {"megaloc": checkpoint}, methods)
    config["backbones"]["megaloc"]["output"] = "features"
    plan = _plan(config)
    (features_key,) = plan.stages["features"]
    with pytest.raises(ValueError) as error:
        run_stage(plan, "features", features_key, tmp_path / "data", tmp_path / "c", {})
    message = str(error.value)
    assert "ref/0001.png is 70 x 50" in message and "ref/0000.png is 64 x 48" in message
    assert "(and 2 more images differ)" in message
    assert "resolution: own" in message and "`resolution: [width, height]`" in message
    assert not (tmp_path / "c" / "features" / f"{features_key}.zarr").exists()
    config["backbones"]["megaloc"]["resolution"] = "dataset"
    plan = _plan(config)
    (features_key,) = plan.stages["features"]
    done: dict = {}
    run_stage(plan, "features", features_key, tmp_path / "data", tmp_path / "c", done)
    features = stores.open_store(done["features", features_key])
    assert features["features"].shape[:3] == (8, 3, 5)  # 64 x 48 rounded to 70 x 42
    assert features.attrs["image_size"] == [48, 64]


def _plan(config: dict):
    return build_plan(validate_config(config, SCHEMA))


def _features_keys(config: dict) -> set[str]:
    return set(_plan(config).stages["features"])


def test_the_checkpoints_content_and_the_output_are_in_the_features_key(tmp_path):
    checkpoint = tmp_path / "dino_salad.ckpt"
    checkpoint.write_bytes(b"one")
    config = trained_config(
        tmp_path, {"salad": checkpoint}, {"own": {"aggregator": "model", "features": "salad"}}
    )
    before = _features_keys(config)
    checkpoint.write_bytes(b"two")  # same path, other weights
    after = _features_keys(config)
    assert before != after
    dense = copy.deepcopy(config)
    dense["backbones"]["salad"]["output"] = "features"
    dense["methods"] = {"own": {"aggregator": "gem", "features": "salad"}}
    assert _features_keys(dense).isdisjoint(after)
    # The published input size is the default resolution, and stated in the key.
    (stage,) = _plan(config).stages["features"].values()
    assert stage.record["params"]["resolution"] == [322, 322]
    assert stage.record["params"]["checkpoint_sha256"]
    assert stage.run_params["uses_gpu"]


@pytest.mark.parametrize(
    ("method", "output", "named"),
    [
        ({"aggregator": "model", "features": "daisy"}, None, r"backbone entry 'daisy'"),
        ({"aggregator": "model", "features": "salad"}, "features", r"output: features"),
        ({"aggregator": "anyloc_vlad", "features": "salad"}, None, r"backbones.salad.output"),
        ({"aggregator": "segvlad", "features": "salad"}, None, r"aggregator 'model'"),
    ],
)
def test_a_reader_that_cannot_read_the_backbones_output_is_refused(tmp_path, method, output, named):
    checkpoint = tmp_path / "dino_salad.ckpt"
    checkpoint.write_bytes(b"weights")
    config = trained_config(tmp_path, {"salad": checkpoint}, {"m": method})
    if output:
        config["backbones"]["salad"]["output"] = output
    with pytest.raises(PlanError, match=named) as error:
        _plan(config)
    assert "method 'm'" in str(error.value)


def test_a_reranker_on_a_models_descriptor_is_refused(tmp_path):
    checkpoint = tmp_path / "dino_salad.ckpt"
    checkpoint.write_bytes(b"weights")
    config = trained_config(
        tmp_path,
        {"salad": checkpoint},
        {"own": {"aggregator": "model", "features": "salad"}},
        rerank={"own": ["mnn"]},
    )
    config["rerankers"] = {"mnn": {"kind": "mnn", "features": "salad"}}
    with pytest.raises(PlanError, match=r"re-ranker 'mnn'.*backbones.salad.output: features"):
        _plan(config)


@pytest.mark.parametrize("given", [None, "absent.ckpt"])
def test_a_missing_checkpoint_is_named_at_plan_time_with_where_to_get_it(tmp_path, given):
    config = trained_config(tmp_path, {}, {"own": {"aggregator": "model", "features": "nv"}})
    config["backbones"]["nv"] = {"backbone": "netvlad", "variant": "patchnetvlad-pitts30k-512"}
    if given:
        config["backbones"]["nv"]["checkpoint"] = str(tmp_path / given)
    with pytest.raises(PlanError) as error:
        _plan(config)
    message = str(error.value)
    assert "backbones.nv.checkpoint" in message
    assert "pitts_WPCA512.pth.tar" in message and "QVPR/Patch-NetVLAD" in message
    assert netvlad.VARIANTS["patchnetvlad-pitts30k-512"].published.url in message
    if given:
        assert given in message


def test_an_unknown_variant_is_refused_listing_the_kinds(tmp_path):
    checkpoint = tmp_path / "c.pth"
    checkpoint.write_bytes(b"weights")
    config = trained_config(
        tmp_path, {"netvlad": checkpoint}, {"own": {"aggregator": "model", "features": "netvlad"}}
    )
    config["backbones"]["netvlad"]["variant"] = "pitts250k"
    with pytest.raises(PlanError, match=r"backbones.netvlad.variant = 'pitts250k'.*nanne-pitts30k"):
        _plan(config)


def test_the_adapter_names_the_expected_file_when_no_checkpoint_is_given():
    from vprflow.models.loaders import load_model

    with pytest.raises(CheckpointError, match=r"dino_salad.ckpt \(serizba/salad\), from https"):
        load_model("features", {"backbone": "salad"}, "cpu")


def test_a_models_own_loader_error_reaches_the_features_stage(tmp_path):
    """A file of another layout is named by the model's loader, with its URL."""
    from vprflow.models.loaders import load_model

    wrong = tmp_path / "dino_salad.ckpt"
    torch.save({"something": torch.zeros(1)}, wrong)
    with pytest.raises(CheckpointError, match=kinds.trained_model("salad").published().url):
        load_model("features", {"backbone": "salad", "checkpoint": str(wrong)}, "cpu")


def test_the_example_config_adds_every_trained_model_and_names_missing_checkpoints(tmp_path):
    """config/trained.yaml over config/config.yaml (as Snakemake merges two config
    files): valid, one row per trained model, and without the checkpoints the plan names
    the first missing file and where to get it."""
    import yaml

    from vprflow.planning.plan import deep_merge

    base = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    extra = yaml.safe_load((REPO / "config" / "trained.yaml").read_text())
    config = deep_merge(base, extra)
    config["datasets"]["corridor"]["methods"] = extra["datasets"]["corridor"]["methods"]
    config["data_root"] = str(tmp_path)
    trained = {e["backbone"] for e in extra["backbones"].values()}
    assert trained == set(kinds.TRAINED_KINDS)
    filled = validate_config(config, SCHEMA)
    with pytest.raises(
        PlanError, match=r"backbones\.netvlad\.checkpoint.*pitts_WPCA4096\.pth\.tar"
    ):
        build_plan(filled)
    for entry in filled["backbones"].values():
        if entry["backbone"] in trained:
            path = tmp_path / entry["checkpoint"]
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(entry["checkpoint"].encode())
            entry["checkpoint"] = str(path)
    rows = [run.method for run in build_plan(filled).runs["corridor"]]
    assert {"netvlad", "salad", "boq_dinov2", "megaloc", "salad+mnn"} <= set(rows)


@pytest.mark.parametrize(
    ("kind", "size"),
    [
        ("mixvpr", (320, 320)),  # its mixer's positions fix the input size
        ("convap", (96, 64)),
        ("boq_resnet50", (96, 64)),
        ("cosplace", (96, 64)),
        ("eigenplaces", (96, 64)),
    ],
)
def test_the_resnet_models_through_the_adapter_are_their_forward_and_their_map(
    kind, size, tmp_path
):
    """The ResNet-50 models at their published sizes (their loaders build no other),
    default random weights saved as a plain state dict: the adapter's descriptor is the
    model's forward on the ImageNet-normalised pixels, and its dense map has its
    entry's stride."""
    from vprflow.models.loaders import load_model
    from vprflow.models.trained import boq, convap, cosplace, mixvpr

    build = {
        "mixvpr": mixvpr.MixVPR,
        "convap": convap.ConvAP,
        "boq_resnet50": boq.BoQResNet,
        "cosplace": cosplace.GeoLocalizationNet,
        "eigenplaces": cosplace.GeoLocalizationNet,
    }[kind]
    torch.manual_seed(0)
    source = build().eval()
    path = tmp_path / "weights.pth"
    torch.save(source.state_dict(), path)
    width, height = size
    pixels = np.random.default_rng(0).random((2, height, width, 3), dtype=np.float32)
    entry = {"backbone": kind, "checkpoint": str(path)}
    got = load_model("features", entry, "cpu").features(pixels)
    x = torch.cat([imagenet(image, source) for image in pixels])
    with torch.no_grad():
        expected = source(x).numpy()
    assert got.shape == (2, 1, 1, source.dim)
    np.testing.assert_allclose(got[:, 0, 0], expected, rtol=0, atol=FLOAT32_ATOL)
    dense = load_model("features", {**entry, "output": "features"}, "cpu").features(pixels)
    stride = kinds.BACKBONES[kind].spec.patch_size
    assert dense.shape[1:3] == (-(-height // stride), -(-width // stride))


def test_the_imagenet_resnet50_gives_the_map_of_its_layer(tmp_path):
    """``resnet50`` (torchvision's layout) stores the map of ``layer`` (1-4, layer3 by
    default as SNSM's baseline), per-patch L2-normalised, with that layer's stride."""
    from vprflow.models.loaders import load_model
    from vprflow.models.trunks.resnet import ResNet

    torch.manual_seed(0)
    source = ResNet(50, "layer4", classifier=True).eval()
    path = tmp_path / "resnet50-0676ba61.pth"
    torch.save(source.state_dict(), path)
    pixels = np.random.default_rng(0).random((2, 64, 96, 3), dtype=np.float32)
    imagenet_stats = netvlad.NetVLADModel(4, None, encoder=_netvlad_encoder(), encoder_dim=8)
    x = torch.cat([imagenet(image, imagenet_stats) for image in pixels])
    for layer, stride in ((3, 16), (1, 4)):
        entry = {"backbone": "resnet50", "checkpoint": str(path)}
        if layer != 3:
            entry["layer"] = layer
        backbone = load_model("features", entry, "cpu")
        with torch.no_grad():
            expected = source.feature_map(x, f"layer{layer}").permute(0, 2, 3, 1).numpy()
        expected = expected / np.linalg.norm(expected, axis=-1, keepdims=True)
        assert backbone.patch_size == stride
        np.testing.assert_allclose(backbone.features(pixels), expected, rtol=0, atol=FLOAT32_ATOL)


def test_a_trained_model_reads_contiguous_channels_first_pixels_as_to_tensor_gives_them(
    tmp_path, monkeypatch
):
    """The adapter fed the trunk a permuted view of ``[B, H, W, 3]``, channels-last in
    memory, where torchvision's ``ToTensor`` and ``Normalize`` give the authors' models a
    contiguous tensor: a ResNet's convolutions take other kernels on it (published
    weights, layer 3: 2.4e-4 apart). The input is now the contiguous one, value for
    value, and so is the map."""
    from vprflow.models.loaders import load_model
    from vprflow.models.trunks.resnet import ResNet

    torch.manual_seed(0)
    source = ResNet(50, "layer3").eval()
    path = tmp_path / "resnet50-0676ba61.pth"
    torch.save(source.state_dict(), path)
    entry = {"backbone": "resnet50", "checkpoint": str(path), "normalize": False}
    backbone = load_model("features", entry, "cpu")
    fed = []
    feature_map = backbone.model.feature_map
    monkeypatch.setattr(
        backbone.model, "feature_map", lambda x, **kw: fed.append(x) or feature_map(x, **kw)
    )
    pixels = np.random.default_rng(0).random((2, 64, 96, 3), dtype=np.float32)
    got = backbone.features(pixels)
    mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    # ToTensor: the image's channels first, contiguous; Normalize: (x - mean) / std.
    reference = (torch.from_numpy(pixels).permute(0, 3, 1, 2).contiguous() - mean) / std
    (x,) = fed
    assert x.is_contiguous() and torch.equal(x, reference)
    with torch.no_grad():
        expected = source.feature_map(reference, "layer3").permute(0, 2, 3, 1).numpy()
    np.testing.assert_array_equal(got, expected)


def test_the_resnet50_trunk_plans_its_layer_and_refuses_a_descriptor(tmp_path):
    checkpoint = tmp_path / "resnet50-0676ba61.pth"
    checkpoint.write_bytes(b"weights")
    config = trained_config(
        tmp_path, {"resnet50": checkpoint}, {"m": {"aggregator": "snsm", "features": "resnet50"}}
    )
    layer3 = _features_keys(config)
    layer2 = copy.deepcopy(config)
    layer2["backbones"]["resnet50"]["layer"] = 2
    assert _features_keys(layer2).isdisjoint(layer3)
    wrong = copy.deepcopy(config)
    wrong["backbones"]["resnet50"]["layer"] = 5
    with pytest.raises(PlanError, match=r"backbones.resnet50.layer = 5.*\[1, 2, 3, 4\]"):
        _plan(wrong)
    own = copy.deepcopy(config)
    own["backbones"]["resnet50"]["output"] = "descriptor"
    own["methods"] = {"m": {"aggregator": "model", "features": "resnet50"}}
    with pytest.raises(PlanError, match=r"backbones.resnet50.output = 'descriptor'.*no descriptor"):
        _plan(own)
