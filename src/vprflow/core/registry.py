"""Every component vprflow knows, in one place: model kinds, aggregators, search
indexes and re-rankers, one entry each.

The plan (which stages a method needs, what each key covers), the stages (which
function computes a descriptor, which loader builds a model), the GPU request, the
weight fingerprints and the schema's enums all read this module;
``tests/test_registry.py`` checks that ``workflow/schemas/config.schema.yaml`` agrees.

What adding each kind of component touches: docs/ARCHITECTURE.md, "What adding a
component touches".

Only data and lazy ``"module:function"`` references live here, so that planning a
workflow never imports torch. Those strings are ties an import graph does not show (the
loaders and score functions import this module back): :func:`references` lists every
one of them, and ``tests/test_registry.py`` imports each.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

# ------------------------------------------------------------------ model kinds


@dataclass(frozen=True)
class ModelKind:
    """A backbone (``role="backbone"``) or segmenter (``role="segmenter"``) kind.

    ``loader`` is ``"module:function"`` with signature ``(params, device) -> model``;
    ``None`` for ``import``, which reads the authors' published HDF5 file instead.
    ``defaults`` are filled into every config entry of this kind before hashing, so a
    key records what ran. ``weights`` says what identifies the model's output beyond
    its parameters: ``"model"`` (hub id, or a local directory hashed by content),
    ``"file"`` (the imported file, hashed), ``"checkpoint"`` (a trained model's
    ``checkpoint`` file, hashed by the plan, which names the expected file and where to
    get it when the entry has none or it is missing) or ``"none"`` (weight-free).
    ``model_files``:
    files of a local model directory besides ``config.json`` and the weights that change
    the output (hashed into the key when present). ``spec``: what the kind's loader
    needs beyond the config entry (a :class:`VitFamily`, a :class:`SamKind`, a
    :class:`TrainedModel`), so one loader serves several kinds and each kind is named
    only here.
    """

    name: str
    role: str
    loader: str | None
    defaults: dict = field(default_factory=dict)
    weights: str = "none"
    uses_gpu: bool = False
    model_files: tuple[str, ...] = ()
    spec: VitFamily | SamKind | TrainedModel | None = None

    def load(self, params: dict, device: str = "auto"):
        if self.loader is None:
            raise ValueError(f"{self.role} {self.name!r} reads a file; it has no model to load")
        return resolve(self.loader)(params, device)


@dataclass(frozen=True)
class VitFamily:
    """What differs between the ViT backbones :func:`vprflow.models.vit.load_vit` loads.

    ``model_types``: the transformers ``model_type`` values a model of this backbone may
    have, each with whether its transformers position-embedding interpolation differs
    from the original repository's (and is replaced under ``pos_embed_interpolation:
    original``); "dinov2_with_registers" already matches. ``rope``: positions from RoPE,
    no position embeddings to interpolate. ``model_normalisation``: mean/std from the
    model's preprocessor_config.json, else ImageNet's. ``hub_checkpoint``: takes a
    torch-hub-layout ``checkpoint`` (SegVLAD-FineT). ``pooler``: False when the
    checkpoints carry no pooler (skips a spurious random initialisation).
    """

    model_types: dict[str, bool]
    rope: bool = False
    model_normalisation: bool = False
    hub_checkpoint: bool = False
    pooler: bool = True


@dataclass(frozen=True)
class SamKind:
    """What differs between the SAM kinds :func:`vprflow.models.sam.adapters.load_sam`
    loads: the transformers model class, the adapter class (``"module:Class"``, see
    :mod:`vprflow.models.sam.adapters`) and the config keys passed to its constructor."""

    model_class: str
    adapter: str
    adapter_options: tuple[str, ...] = ()


@dataclass(frozen=True)
class TrainedVariant:
    """One published checkpoint of a trained model: its file name, where to get it, the
    repository that publishes it, and the keyword arguments its ``load_<model>`` takes
    for it (NetVLAD: ``variant``).

    ``direct``: ``url`` serves the file itself, so the ``trained_checkpoint`` rule fetches
    it; False for a page a person downloads from (Google Drive). ``sha256``: the SHA-256
    the publisher states, or the first hex digits of it where that is all it states (a
    torchvision file name); None where vprflow has none on record, and then the fetched
    file's hash is logged, not checked.
    """

    file: str
    url: str
    repository: str
    loader_options: dict = field(default_factory=dict)
    direct: bool = True
    sha256: str | None = None


@dataclass(frozen=True)
class TrainedModel:
    """A trained VPR model (issue 32) as a backbone kind, wrapped into the backbone
    interface by :func:`vprflow.models.trained.backbone.load_trained`.

    ``loader``: ``"module:function"`` with signature ``(checkpoint path, **variant
    loader_options) -> nn.Module`` whose ``forward`` takes ImageNet-normalised
    ``[B, 3, H, W]`` and returns the L2-normalised descriptor ``[B, D]``, and whose
    ``feature_map`` returns the dense map its head reads ``[B, C, h, w]`` (``dense``
    says which), with ``mean`` / ``std`` attributes. ``variants``: the published
    checkpoints by name (the first is the default). ``input_size``: the published input
    ``(width, height)``, the default of the entry's ``resolution`` (the model modules'
    ``INPUT_SIZE`` is ``(height, width)``; test_registry compares them); ``None``: the
    published evaluation feeds the images at their own size (the dataset's). ``patch_size``:
    the stride of ``feature_map``. ``crop``: centre-crop an input to whole patches
    first, as vprflow's ViT backbones do (DINOv2 needs multiples of 14; MegaLoc resizes
    to them itself, so False). ``resize``: the published reader's resize (a
    :data:`vprflow.data.images.RESIZE_METHODS` name), what ``resize: method`` means
    under the ``model`` aggregator. ``layer_strides``: for a trunk whose entry picks
    the map with ``layer`` (ResNet-50: 1-4), each layer's stride (``patch_size`` is
    the default layer's); its loader takes ``end="layer<k>"`` and its ``feature_map``
    ``layer="layer<k>"``; ``None``: the model's own map. ``descriptor``: False for a
    trunk with no descriptor of its own (``output: features`` only).
    """

    loader: str
    variants: dict[str, TrainedVariant]
    input_size: tuple[int, int] | None
    patch_size: int
    dense: str
    crop: bool = True
    resize: str = "antialias"
    layer_strides: dict[int, int] | None = None
    descriptor: bool = True

    @property
    def default_variant(self) -> str:
        return next(iter(self.variants))


# The ViT backbones' choices: which projection is read, how position embeddings are
# interpolated (vprflow.models.vit; here so that the schema lists them without torch).
FACETS = ("query", "key", "value", "token")
POS_EMBED_INTERPOLATIONS = ("original", "transformers")

_VIT = {
    "facet": "value",
    "final_norm": False,
    "dtype": "float32",
    "pos_embed_interpolation": "original",
    "cache_dir": None,
}

# Segment Anything's automatic mask generator defaults (segment-anything's
# SamAutomaticMaskGenerator), shared by the SAM-family segmenters unless noted.
_SAM_GENERATOR = {
    "cache_dir": None,
    "points_per_side": 32,
    "points_per_batch": 64,
    "pred_iou_thresh": 0.88,
    "stability_score_thresh": 0.95,
    "stability_score_offset": 1.0,
    "box_nms_thresh": 0.7,
    "min_mask_region_area": 0,
    "mask_threshold": 0.0,
    "dtype": "float32",
}

# What a trained kind's features store holds: the model's own descriptor (one 1 x 1 x D
# grid per image, for the `model` aggregator) or the dense map its head reads (for
# AnyLoc-VLAD, SegVLAD, SNSM, pooling and re-ranking).
TRAINED_OUTPUTS = ("descriptor", "features")

_TRAINED = "vprflow.models.trained"
# The published CosPlace and EigenPlaces models: ResNet backbone -> descriptor lengths
# (vprflow.models.trained.cosplace's, restated torch-free; test_registry compares).
_COSPLACE_DIMS = {
    "ResNet18": (32, 64, 128, 256, 512),
    **{b: (32, 64, 128, 256, 512, 1024, 2048) for b in ("ResNet50", "ResNet101", "ResNet152")},
}
_EIGENPLACES_DIMS = {
    "ResNet18": (256, 512),
    **{b: (128, 256, 512, 1024, 2048) for b in ("ResNet50", "ResNet101")},
}
_PATCH_NETVLAD = "https://huggingface.co/TobiasRobotics/Patch-NetVLAD/resolve/main/"


def _netvlad(name: str, file: str) -> tuple[str, TrainedVariant]:
    return name, TrainedVariant(
        file, _PATCH_NETVLAD + file, "QVPR/Patch-NetVLAD", {"variant": name}
    )


# The trained VPR models (docs/methods.md, "Trained models"); each module's own
# constants (URL, file, input size) are compared with these by tests/test_registry.py.
_TRAINED_MODELS: dict[str, TrainedModel] = {
    # VGG16 conv5_3 + NetVLAD (+ whitening), Pittsburgh 30k; Patch-NetVLAD reads images
    # with PIL and resizes them to 640 x 480 with torchvision's Resize (antialiased).
    "netvlad": TrainedModel(
        f"{_TRAINED}.netvlad:load_netvlad",
        dict(
            [
                _netvlad("patchnetvlad-pitts30k-4096", "pitts_WPCA4096.pth.tar"),
                _netvlad("patchnetvlad-pitts30k-32768", "pitts_WPCA4096.pth.tar"),
                _netvlad("patchnetvlad-pitts30k-512", "pitts_WPCA512.pth.tar"),
                _netvlad("patchnetvlad-pitts30k-128", "pitts_WPCA128.pth.tar"),
                (
                    "nanne-pitts30k",
                    TrainedVariant(
                        "checkpoint.pth.tar",
                        "https://drive.google.com/open?id=17luTjZFCX639guSVy00OUtzfTQo4AMF2",
                        "Nanne/pytorch-NetVlad",
                        {"variant": "nanne-pitts30k"},
                        direct=False,
                    ),
                ),
            ]
        ),
        (640, 480),
        16,
        "VGG16 conv5_3, 512-d, stride 16 (before its ReLU)",
        crop=False,
    ),
    # DINOv2-B/14 + optimal-transport aggregation; evaluated at 322 x 322 (PIL bilinear).
    "salad": TrainedModel(
        f"{_TRAINED}.salad:load_salad",
        {
            "dino_salad": TrainedVariant(
                "dino_salad.ckpt",
                "https://github.com/serizba/salad/releases/download/v1.0.0/dino_salad.ckpt",
                "serizba/salad",
            )
        },
        (322, 322),
        14,
        "DINOv2-B/14 patch tokens after the final LayerNorm, 768-d",
    ),
    # DINOv2-B/14 (no final norm) + Bag-of-Queries; BoQ resizes bicubically (antialiased),
    # which vprflow's resize methods lack: bilinear antialiased here.
    "boq_dinov2": TrainedModel(
        f"{_TRAINED}.boq_dinov2:load_boq_dinov2",
        {
            "dinov2_12288": TrainedVariant(
                "dinov2_12288.pth",
                "https://github.com/amaralibey/Bag-of-Queries/releases/download/v1.0/"
                "dinov2_12288.pth",
                "amaralibey/Bag-of-Queries",
            )
        },
        (322, 322),
        14,
        "DINOv2-B/14 last-block patch tokens (no final LayerNorm), 768-d",
    ),
    # DINOv2-B/14 + SALAD-style aggregation + linear projection, at the images' own size
    # (VPR-methods-evaluation resizes nothing by default; MegaLoc rounds each side to a
    # multiple of 14 itself, so no crop).
    "megaloc": TrainedModel(
        f"{_TRAINED}.megaloc:load_megaloc",
        {
            "megaloc": TrainedVariant(
                "model.safetensors",
                "https://huggingface.co/gberton/MegaLoc/resolve/main/model.safetensors",
                "gmberton/MegaLoc",
            )
        },
        None,
        14,
        "DINOv2-B/14 patch tokens after the final LayerNorm, 768-d",
        crop=False,
    ),
    # ResNet-50 cut after layer3 + feature mixing (4096-d), GSV-Cities; 320 x 320 (its
    # mixer's 20 x 20 positions fix the input size).
    "mixvpr": TrainedModel(
        f"{_TRAINED}.mixvpr:load_mixvpr",
        {
            "resnet50_4096": TrainedVariant(
                "resnet50_MixVPR_4096_channels(1024)_rows(4).ckpt",
                "https://drive.google.com/file/d/1vuz3PvnR7vxnDDLQrdHJaOA04SQrtk5L/view",
                "amaralibey/MixVPR",
                direct=False,
            )
        },
        (320, 320),
        16,
        "ResNet-50 layer3, 1024-d, stride 16",
        crop=False,
    ),
    # ResNet-50 (to layer4) + Conv-AP (4096-d: 1024 channels x 2 x 2), GSV-Cities; the
    # gsv-cities README documents only this file's name.
    "convap": TrainedModel(
        f"{_TRAINED}.convap:load_convap",
        {
            "resnet50_4096": TrainedVariant(
                "resnet50_ConvAP_1024_2x2.ckpt",
                "https://drive.google.com/drive/folders/1VYPw9uGD11NgiGFgfWueLt3noJYOIuhL",
                "amaralibey/gsv-cities",
                {"dim": 4096},
                direct=False,
            )
        },
        (320, 320),
        32,
        "ResNet-50 layer4, 2048-d, stride 32",
        crop=False,
    ),
    # ResNet-50 cut after layer3 + Bag-of-Queries, 16384-d, 384 x 384.
    "boq_resnet50": TrainedModel(
        f"{_TRAINED}.boq:load_boq_resnet50",
        {
            "resnet50_16384": TrainedVariant(
                "resnet50_16384.pth",
                "https://github.com/amaralibey/Bag-of-Queries/releases/download/v1.0/"
                "resnet50_16384.pth",
                "amaralibey/Bag-of-Queries",
            )
        },
        (384, 384),
        16,
        "ResNet-50 layer3, 1024-d, stride 16",
        crop=False,
    ),
    # ResNet trunk + GeM + FC, at the images' own size (their evaluation resizes
    # nothing); one variant per published backbone and length, ResNet50_2048 first.
    **{
        name.lower(): TrainedModel(
            loader,
            {
                f"{backbone}_{dim}": TrainedVariant(
                    f"{backbone}_{dim}_{name.lower()}.pth",
                    f"https://github.com/gmberton/{name}/releases/download/v1.0/"
                    f"{backbone}_{dim}_{name.lower()}.pth",
                    f"gmberton/{name}",
                    {"backbone": backbone, "dim": dim},
                )
                for backbone, dim in sorted(
                    ((b, d) for b, dims in published.items() for d in dims),
                    key=lambda v: v != ("ResNet50", 2048),
                )
            },
            None,
            32,
            "the ResNet's layer4 (ResNet-50: 2048-d), stride 32",
            crop=False,
        )
        for name, published, loader in (
            ("CosPlace", _COSPLACE_DIMS, f"{_TRAINED}.cosplace:load_cosplace"),
            ("EigenPlaces", _EIGENPLACES_DIMS, f"{_TRAINED}.cosplace:load_eigenplaces"),
        )
    },
    # torchvision's ImageNet ResNet-50 as dense features only: the map of `layer` 1-4
    # (SNSM's All-Backbones-VLAD baseline reads layer1-4, layer3 by default), at the
    # dataset's resolution as SNSM reads it.
    "resnet50": TrainedModel(
        "vprflow.models.trunks.resnet:load_resnet",
        {
            "imagenet1k_v1": TrainedVariant(
                "resnet50-0676ba61.pth",
                "https://download.pytorch.org/models/resnet50-0676ba61.pth",
                "pytorch/vision",
                {"depth": 50},
                # torchvision names its files after their SHA-256's first 8 hex digits.
                sha256="0676ba61",
            )
        },
        None,
        16,
        "the ImageNet ResNet-50's `layer` map (layer1-4: 256-2048-d, stride 4-32)",
        crop=False,
        layer_strides={1: 4, 2: 8, 3: 16, 4: 32},
        descriptor=False,
    ),
}


def _trained(name: str, spec: TrainedModel) -> ModelKind:
    """A trained model's backbone kind: one loader serves them all."""
    return ModelKind(
        name,
        "backbone",
        f"{_TRAINED}.backbone:load_trained",
        {
            "checkpoint": None,
            "variant": spec.default_variant,
            # A trunk has no descriptor of its own: its dense map.
            "output": TRAINED_OUTPUTS[0] if spec.descriptor else "features",
            **({"resolution": list(spec.input_size)} if spec.input_size else {}),
            # The default layer: the one whose stride is the spec's patch size.
            **(
                {"layer": next(k for k, v in spec.layer_strides.items() if v == spec.patch_size)}
                if spec.layer_strides
                else {}
            ),
        },
        weights="checkpoint",
        uses_gpu=True,
        spec=spec,
    )


BACKBONES: dict[str, ModelKind] = {
    kind.name: kind
    for kind in (
        ModelKind(
            "daisy",
            "backbone",
            "vprflow.models.backbones:load_daisy",
            {"patch_size": 8, "radius": 12, "rings": 2, "histograms": 6, "orientations": 8},
        ),
        # AnyLoc / SegVLAD: value facet of block 31 (0-based) of ViT-G/14's 40.
        ModelKind(
            "dinov2",
            "backbone",
            "vprflow.models.vit:load_vit",
            {"model": "facebook/dinov2-giant", "layer": 31, **_VIT},
            weights="model",
            uses_gpu=True,
            spec=VitFamily({"dinov2": True, "dinov2_with_registers": False}, hub_checkpoint=True),
        ),
        # DINOv3 ViT-L/16 (24 blocks): block 18 (0-based) runs 19 of 24, the depth of
        # AnyLoc's 31 of 40 (32 of 40 run); RoPE, so no pos_embed_interpolation. Its
        # mean/std come from preprocessor_config.json when the directory has one.
        ModelKind(
            "dinov3",
            "backbone",
            "vprflow.models.vit:load_vit",
            {
                "model": "facebook/dinov3-vitl16-pretrain-lvd1689m",
                "layer": 18,
                **{k: v for k, v in _VIT.items() if k != "pos_embed_interpolation"},
            },
            weights="model",
            uses_gpu=True,
            model_files=("preprocessor_config.json",),
            spec=VitFamily({"dinov3_vit": False}, rope=True, model_normalisation=True),
        ),
        # DINO v1: the last block (-1 counts from the end).
        ModelKind(
            "dino",
            "backbone",
            "vprflow.models.vit:load_vit",
            {"model": "facebook/dino-vitb8", "layer": -1, **_VIT},
            weights="model",
            uses_gpu=True,
            spec=VitFamily({"vit": True}, pooler=False),
        ),
        ModelKind("import", "backbone", None, {"patch_size": 14}, weights="file"),
        *(_trained(name, spec) for name, spec in _TRAINED_MODELS.items()),
    )
}

# The trained models' backbone kinds, in registry order (the schema's x-kinds of the
# keys they read name this constant).
TRAINED_KINDS = tuple(n for n, k in BACKBONES.items() if isinstance(k.spec, TrainedModel))

_SAM_ADAPTERS = "vprflow.models.sam.adapters"
_SAM_LOADER = f"{_SAM_ADAPTERS}:load_sam"

SEGMENTERS: dict[str, ModelKind] = {
    kind.name: kind
    for kind in (
        ModelKind(
            "slic",
            "segmenter",
            "vprflow.models.segmenters:load_slic",
            {"n_segments": 50, "compactness": 10.0, "sigma": 1.0},
        ),
        ModelKind(
            "felzenszwalb",
            "segmenter",
            "vprflow.models.segmenters:load_felzenszwalb",
            {"scale": 100.0, "sigma": 0.8, "min_size": 50},
        ),
        # The original automatic mask generator's defaults (ViT-H).
        ModelKind(
            "sam",
            "segmenter",
            _SAM_LOADER,
            {"model": "facebook/sam-vit-huge", **_SAM_GENERATOR},
            weights="model",
            uses_gpu=True,
            spec=SamKind("SamModel", f"{_SAM_ADAPTERS}:SamAdapter"),
        ),
        # SAM-HQ's automatic mask generator (SAM's, defaults unchanged) on the HQ decoder:
        # one mask per point, best multimask logits + HQ logits (hq_token_only off).
        ModelKind(
            "sam_hq",
            "segmenter",
            _SAM_LOADER,
            {"model": "syscv-community/sam-hq-vit-huge", **_SAM_GENERATOR, "hq_token_only": False},
            weights="model",
            uses_gpu=True,
            spec=SamKind("SamHQModel", f"{_SAM_ADAPTERS}:SamHQAdapter", ("hq_token_only",)),
        ),
        # SAM 2's own automatic mask generator defaults (Hiera-L): pred_iou_thresh 0.8;
        # multimask output on and use_m2m off (fixed here).
        ModelKind(
            "sam2",
            "segmenter",
            _SAM_LOADER,
            {"model": "facebook/sam2.1-hiera-large", **_SAM_GENERATOR, "pred_iou_thresh": 0.8},
            weights="model",
            uses_gpu=True,
            spec=SamKind("Sam2Model", f"{_SAM_ADAPTERS}:Sam2Adapter"),
        ),
        ModelKind("import", "segmenter", None, weights="file"),
    )
}

# The config key that names an entry's kind, and the registry of each stage that runs one.
KIND_KEY = {"features": "backbone", "segments": "segmenter"}
MODEL_STAGES = {"features": BACKBONES, "segments": SEGMENTERS}


def model_kind(stage: str, entry: dict) -> ModelKind:
    """The kind of a backbone entry (``stage="features"``) or segmenter entry
    (``stage="segments"``)."""
    kinds = MODEL_STAGES[stage]
    name = entry[KIND_KEY[stage]]
    if name not in kinds:
        raise ValueError(f"unknown {KIND_KEY[stage]} {name!r}; expected one of {sorted(kinds)}")
    return kinds[name]


def with_defaults(stage: str, entry: dict) -> dict:
    """``entry`` with its kind's defaults filled in where it names none (or ``None``)."""
    filled = dict(entry)
    for name, value in model_kind(stage, entry).defaults.items():
        if filled.get(name) is None:
            filled[name] = value
    return filled


# ------------------------------------------------------------------ aggregators

# The value of a backbone's `resize` and a dataset's `exif_orientation` that defers to
# the method's aggregator (its `resize` / `exif_orientation` below): the published
# pipeline's reader.
BY_METHOD = "method"


@dataclass(frozen=True)
class Aggregator:
    """A method's descriptor: what it needs upstream and what it outputs.

    ``needs``: upstream stages besides ``dataset`` and ``features``, in plan order
    (``pca`` is planned only when the method's ``pca.enabled``). ``output``:
    ``"global"`` (one vector per image) or ``"segments"`` (one per segment, retrieved
    by voting). ``compute``: its per-image function, ``(grid [h, w, D], options,
    **inputs) -> [dim]`` (``[S, dim]`` per segment), ``options`` the descriptor stage's
    params; ``inputs`` are what its ``needs`` give: ``centres`` (``vocabulary``),
    ``masks``, ``image_size`` and ``patch_size`` (``segments``).
    :func:`vprflow.stages.image_descriptors.image_descriptor` reads them and runs it, for
    every aggregator alike. ``options(method)`` is the descriptor stage's own hashed
    settings (method = the resolved method settings); ``columns(method)`` its CSV
    columns.
    ``explanation``: the report's figure of how the method decided, besides the
    retrievals every method gets (a name in :data:`vprflow.planning.reports.FIGURES`), or None.
    ``pca_fit``: see :meth:`pca_descriptor_options` (for aggregators with ``pca``).
    ``resize``: how the published pipeline resizes images before the backbone (a
    :data:`vprflow.data.images.RESIZE_METHODS` name), the default of a backbone's
    ``resize: method``: SegVLAD's and AnyLoc's readers use OpenCV, SNSM's (and its
    pooling baselines') torchvision on PIL images. ``exif_orientation``: whether that
    reader turns images as their EXIF Orientation tag says (a
    :data:`vprflow.data.images.EXIF_ORIENTATIONS` name), the default of a dataset's
    ``exif_orientation: method``: ``cv2.imread`` (SegVLAD, AnyLoc) applies it, SNSM's
    ``PIL.Image.open(...).convert('RGB')`` ignores it. ``reads``: what its features
    store must hold, ``"features"`` (a dense patch grid, every backbone kind's; a trained
    kind's under ``output: features``) or ``"descriptor"`` (a trained model's own
    descriptor, ``output: descriptor``); the plan refuses any other pairing, and for
    ``"descriptor"`` ``resize: method`` is the trained kind's published reader.

    ``sections``: the config sections of its own settings (each a schema definition);
    :data:`vprflow.planning.config.METHOD_DEFAULT_SECTIONS` is derived from them, so a
    new aggregator's section needs no list besides the schema. Left out, ``options`` is
    their values merged and ``columns`` their values as ``<section>.<key>`` columns.
    """

    name: str
    needs: tuple[str, ...]
    output: str
    compute: Callable[..., Any]
    options: Callable[[dict], dict] | None = None
    columns: Callable[[dict], dict] | None = None
    explanation: str | None = None
    resize: str = "linear"
    exif_orientation: str = "apply"
    pca_fit: Callable[[dict, dict], dict] | None = None
    reads: str = "features"
    sections: tuple[str, ...] = ()

    def __post_init__(self):
        # Left out, ``options`` and ``columns`` are the values of its sections.
        sections = self.sections

        def options(method: dict) -> dict:
            return {k: v for s in sections for k, v in method[s].items()}

        def columns(method: dict) -> dict:
            return {k: v for s in sections for k, v in prefixed(s, method[s]).items()}

        if self.options is None:
            object.__setattr__(self, "options", options)
        if self.columns is None:
            object.__setattr__(self, "columns", columns)

    def pca_descriptor_options(self, method: dict, options: dict) -> dict:
        """The descriptor options of the vectors a PCA is fitted on (the PCA stage
        computes them as the descriptors stage does): the method's own, less how
        they are stored, unless the aggregator's ``pca_fit(method, options)`` says
        otherwise (SegVLAD: at ``pca.fit_order``)."""
        if self.pca_fit is not None:
            return self.pca_fit(method, options)
        return {k: v for k, v in options.items() if k != "store_dtype"}


def prefixed(section: str, values: dict) -> dict:
    """CSV columns ``<section>.<key>`` of a settings section."""
    return {f"{section}.{k}": v for k, v in values.items()}


# ------------------------------------------------------------------ search indexes


@dataclass(frozen=True)
class SearchIndex:
    """A ``retrieval.index``: whether it returns the exact top-k (an approximate one makes
    the plan add an exact search, so the table can report the difference), the function
    that runs it, whether it runs on a GPU when there is one, and its parameters'
    defaults (``None``: chosen at run time by its function), filled into a method's
    ``retrieval.params`` before hashing (:func:`search_settings`).

    ``knn`` is ``"module:function"`` with signature ``(database [Nd, D], queries [Nq, D],
    k, **params) -> (distances [Nq, k'] float32, indices [Nq, k'] int64)`` (see
    :mod:`vprflow.search`), plus ``device`` when ``uses_gpu``; :meth:`search` calls it.
    The defaults live here rather than in :mod:`vprflow.search`, whose functions read them:
    planning must fill them into keys without importing torch, as for the model kinds.
    """

    name: str
    exact: bool
    knn: str
    uses_gpu: bool = False
    defaults: dict = field(default_factory=dict)

    def search(self, database, queries, k: int, params: dict | None = None, device="auto"):
        """Squared-L2 ``k`` nearest ``database`` rows of every query with this index and
        ``params`` (left out: :attr:`defaults`): ``(distances [Nq, k'] float32, indices
        [Nq, k'] int64)``, ``k' = min(k, Nd)``, nearest first. Rows of an approximate
        index may end in index -1 (fewer than k found). ``device`` (``"auto"``, ``"cpu"``,
        ``"cuda"``) is used by the indexes that run on a GPU."""
        params = dict(params or {})
        _check_search_params(self, params, "params")
        if self.uses_gpu:
            params["device"] = device
        return resolve(self.knn)(database, queries, k, **params)


_IVF = {"nlist": None, "nprobe": 16, "seed": 1234}
_KNN = "vprflow.search"

SEARCH_INDEXES: dict[str, SearchIndex] = {
    index.name: index
    for index in (
        # faiss IndexFlatL2, published.
        SearchIndex("flat", exact=True, knn=f"{_KNN}.flat:flat_knn"),
        # margin None: by candidate dtype (vprflow.search.exact.DEFAULT_MARGINS).
        # None of these changes the result, only speed and memory.
        SearchIndex(
            "exact_fast",
            exact=True,
            knn=f"{_KNN}.exact:exact_knn",
            uses_gpu=True,
            defaults={
                "candidate_dtype": "bfloat16",
                "block_queries": 4096,
                "block_database": 65536,
                "margin": None,
            },
        ),
        SearchIndex(
            "ivf_flat", exact=False, knn=f"{_KNN}.approximate:ivf_flat_knn", defaults=dict(_IVF)
        ),
        SearchIndex(
            "ivf_pq",
            exact=False,
            knn=f"{_KNN}.approximate:ivf_pq_knn",
            defaults={**_IVF, "m": None, "nbits": 8},
        ),
        SearchIndex(
            "hnsw",
            exact=False,
            knn=f"{_KNN}.approximate:hnsw_knn",
            defaults={"M": 32, "ef_search": 128, "ef_construction": 200},
        ),
    )
}


def search_index(name: str) -> SearchIndex:
    if name not in SEARCH_INDEXES:
        raise ValueError(f"unknown search index {name!r}; expected one of {sorted(SEARCH_INDEXES)}")
    return SEARCH_INDEXES[name]


def search_settings(retrieval: dict) -> dict:
    """A ``retrieval`` section (``index``, ``params``) with the index's parameter defaults
    filled into ``params``, so a key records what ran; a parameter the index does not
    take is refused by name."""
    index = search_index(retrieval["index"])
    params = retrieval["params"]
    _check_search_params(index, params, "retrieval.params")
    return {**retrieval, "params": {**index.defaults, **params}}


def _check_search_params(index: SearchIndex, params: dict, what: str) -> None:
    unknown = sorted(set(params) - set(index.defaults))
    if unknown:
        raise ValueError(
            f"{what} {unknown} are not parameters of index {index.name!r}; "
            f"it takes {sorted(index.defaults) or 'none'}"
        )


@dataclass(frozen=True)
class Reranker:
    """A ``rerankers.<name>.kind``: how it scores a query's candidates.

    ``scores`` is ``"module:function"`` with signature ``(pairs, centres [P, 2], patch,
    **settings) -> scores [K] float64`` (higher is better), ``pairs`` one ``(i [M], j
    [M], similarity [M] float32)`` per candidate: its mutual nearest neighbour patch
    pairs with the query, as :func:`vprflow.evaluation.rerank.candidate_pairs` finds them
    and the ``matches`` stage stores them (:func:`vprflow.evaluation.rerank.pair_scorer`
    binds it for the ``rerank`` stage; an empty ``pairs`` checks the settings alone).
    ``defaults``: the entry's keys that shape its scores, with their defaults
    (``load_schema`` writes them into the schema, so the config's defaults are these);
    the rest of the entry, ``features`` and ``top_k``, reach the key through the plan.
    ``fixed``: the function's further settings, which the config leaves at these values
    (not in the key: only a code change moves them). ``score``: the kind of score stored
    (a :data:`vprflow.evaluation.precision_recall.SCORE_KINDS` name).
    """

    name: str
    scores: str
    defaults: dict
    fixed: dict = field(default_factory=dict)
    score: str = "matches"

    @property
    def options(self) -> tuple[str, ...]:
        """The config keys the kind reads besides ``kind``, ``features`` and ``top_k``."""
        return tuple(self.defaults)

    def settings(self, options: dict) -> dict:
        """Every setting of the score function: ``options`` over the defaults; a key
        the kind does not take is refused by name."""
        known = {**self.defaults, **self.fixed}
        unknown = sorted(set(options) - set(known))
        if unknown:
            raise TypeError(
                f"re-ranker {self.name!r} got unknown options {unknown}; it takes {list(known)}"
            )
        return {**known, **options}


_RERANK = "vprflow.evaluation.rerank"

RERANKERS: dict[str, Reranker] = {
    r.name: r
    for r in (
        # EffoVPR's zero-shot score: the count of mutual pairs at least T2 similar.
        Reranker(
            "mnn",
            f"{_RERANK}:mnn_pair_scores",
            {"weighting": "count", "min_similarity": None},
        ),
        # Patch-NetVLAD's RANSAC score; threshold in patches (1.5, as published). The
        # estimator's budget stays fixed: the config never set it.
        Reranker(
            "ransac",
            f"{_RERANK}:ransac_pair_scores",
            {"min_similarity": None, "threshold": 1.5, "seed": 0},
            fixed={"model": "homography", "max_iters": 2000, "confidence": 0.999},
        ),
    )
}


def reranker(name: str) -> Reranker:
    if name not in RERANKERS:
        raise ValueError(f"unknown re-ranker kind {name!r}; expected one of {sorted(RERANKERS)}")
    return RERANKERS[name]


def resolve(reference: str):
    """The object a ``"module:function"`` reference names (imported on first use)."""
    module, _, name = reference.partition(":")
    return getattr(importlib.import_module(module), name)


def references() -> list[tuple[str, str]]:
    """Every lazy reference of the registry, as ``(where, "module:name")``: each model
    kind's loader and SAM adapter, each aggregator's descriptor function and compute
    function, each search
    index's function and each re-ranker's score function. These modules import the
    registry; the registry names them only by string, so that planning never imports
    torch. This list is what makes those two-way ties visible."""
    found = []
    for role, kinds in (("backbone", BACKBONES), ("segmenter", SEGMENTERS)):
        for kind in kinds.values():
            if kind.loader is not None:
                found.append((f"{role} {kind.name}: loader", kind.loader))
            if isinstance(kind.spec, SamKind):
                found.append((f"{role} {kind.name}: adapter", kind.spec.adapter))
            if isinstance(kind.spec, TrainedModel):
                found.append((f"{role} {kind.name}: model", kind.spec.loader))
    found += [(f"search index {i.name}", i.knn) for i in SEARCH_INDEXES.values()]
    found += [(f"re-ranker {r.name}", r.scores) for r in RERANKERS.values()]
    return found
