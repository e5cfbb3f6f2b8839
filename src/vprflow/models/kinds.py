"""Every model kind vprflow knows, as data: backbones and segmenters, one
:class:`ModelKind` entry each, with its defaults and what its loader needs (a
:class:`VitFamily`, a :class:`SamKind`, a :class:`TrainedModel`).

Torch-free, so that planning fills the defaults into keys, and the schema lists the
kinds, without importing a model: :mod:`vprflow.models.loaders` binds each kind to the
function that loads it, and the model modules read their own entries here
(:func:`with_defaults`). ``tests/planning/test_registry.py`` checks that
``workflow/schemas/config.schema.yaml`` agrees.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class ModelKind:
    """A backbone (``role="backbone"``) or segmenter (``role="segmenter"``) kind.

    ``defaults`` are filled into every config entry of this kind before hashing, so a
    key records what ran. ``weights`` says what identifies the model's output beyond
    its parameters: ``"model"`` (hub id, or a local directory hashed by content),
    ``"file"`` (the imported file, hashed), ``"checkpoint"`` (a trained model's
    ``checkpoint`` file, hashed by the plan, which names the expected file and where to
    get it when the entry has none or it is missing) or ``"none"`` (weight-free);
    ``"file"`` kinds (``import``) load no model. ``version``: the kind's format version.
    ``model_files``: files of a local
    model directory besides ``config.json`` and the weights that change the output
    (hashed into the key when present). ``spec``: what the kind's loader needs beyond
    the config entry (a :class:`VitFamily`, a :class:`SamKind`, a
    :class:`TrainedModel`), so one loader serves several kinds and each kind is named
    only here.
    """

    name: str
    role: str
    defaults: dict = field(default_factory=dict)
    weights: str = "none"
    uses_gpu: bool = False
    model_files: tuple[str, ...] = ()
    spec: VitFamily | SamKind | TrainedModel | None = None
    # The kind's own format version, in its stores' keys from 2 on (so that the keys of
    # the kinds at 1 stand): bump it when the kind's output changes (reasons by kind).
    version: int = 1

    @property
    def reads_file(self) -> bool:
        """``import``: reads the authors' published HDF5 file, no model to load."""
        return self.weights == "file"


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
    loads: the transformers model class (which picks its adapter,
    :data:`vprflow.models.sam.adapters.ADAPTERS`) and the config keys passed to the
    adapter's constructor."""

    model_class: str
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

    @property
    def hint(self) -> str:
        """What a model's loader adds to an error about a file of another layout."""
        return f"expected {self.file} from {self.url}"


@dataclass(frozen=True)
class TrainedModel:
    """A trained VPR model as a backbone kind, wrapped into the backbone interface by
    :func:`vprflow.models.trained.backbone.load_trained`.

    Its loader (:data:`vprflow.models.loaders.TRAINED_MODELS`) takes ``(checkpoint path,
    **variant loader_options)`` and returns an ``nn.Module`` whose ``forward`` takes
    ImageNet-normalised ``[B, 3, H, W]`` and returns the L2-normalised descriptor ``[B,
    D]``, and whose ``feature_map`` returns the dense map its head reads ``[B, C, h,
    w]`` (``dense`` says which), with ``mean`` / ``std`` attributes. ``variants``: the
    published checkpoints by name (the first is the default). ``input_size``: the
    published input ``(width, height)``, the default of the entry's ``resolution`` (the
    model module's ``INPUT_SIZE`` reads it, :attr:`height_width`); ``None``: the
    dataset's (``resolution: dataset``), or each image's own where
    ``own_size``: the published evaluation feeds every image at its own size, so the
    entry's default ``resolution`` is :data:`OWN_SIZE`. ``patch_size``: the stride of
    ``feature_map``. ``crop``: centre-crop an input to whole patches first, as
    vprflow's ViT backbones do (DINOv2 needs multiples of 14; MegaLoc resizes to them
    itself, so False). ``resize``: the published reader's
    resize (a :data:`vprflow.data.images.RESIZE_METHODS` name), what ``resize: method``
    means under the ``model`` aggregator. ``layer_strides``: for a trunk whose entry
    picks the map with ``layer`` (ResNet-50: 1-4), each layer's stride (``patch_size``
    is the default layer's); its loader takes ``end="layer<k>"`` and its ``feature_map``
    ``layer="layer<k>"``; ``None``: the model's own map. ``descriptor``: False for a
    trunk with no descriptor of its own (``output: features`` only).
    """

    variants: dict[str, TrainedVariant]
    input_size: tuple[int, int] | None
    patch_size: int
    dense: str
    crop: bool = True
    resize: str = "antialias"
    layer_strides: dict[int, int] | None = None
    descriptor: bool = True
    own_size: bool = False

    @property
    def default_variant(self) -> str:
        return next(iter(self.variants))

    @property
    def height_width(self) -> tuple[int, int] | None:
        """:attr:`input_size` as ``(height, width)``, the order of torch's maps."""
        return None if self.input_size is None else (self.input_size[1], self.input_size[0])

    def published(self, variant: str | None = None) -> TrainedVariant:
        """The published checkpoint of ``variant`` (the default one when None)."""
        return self.variants[variant or self.default_variant]


# A backbone entry's `resolution` that resizes nothing: each image at its own size (after
# its EXIF orientation), as MegaLoc's, CosPlace's and EigenPlaces' evaluations read it. A
# dense map (output: features) then needs one size for every image: later stages stack it.
OWN_SIZE = "own"

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

# The published CosPlace and EigenPlaces models: ResNet backbone -> descriptor lengths.
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


VLAD_BUFF_RELEASE = "https://github.com/ahmedest61/VLAD-BuFF/releases/download/v1.0.0/"
# VLAD-BuFF's published checkpoints: pre-pool PCA dims (None: none) -> whitened dims, the
# pairs hubconf.vlad_buff accepts.
VLAD_BUFF_PCS = {None: 8192, 192: 4096}


def vlad_buff_file(nv_pca: int | None, num_pcs: int | None = None) -> str:
    """A VLAD-BuFF checkpoint's file name as ``hubconf.vlad_buff`` builds it; ``num_pcs``
    None: the whitening published with ``nv_pca`` (the file holds the VLAD's weights too)."""
    pcs = num_pcs if num_pcs is not None else VLAD_BUFF_PCS.get(nv_pca, "<n>")
    pca = "" if nv_pca is None else f"{nv_pca}PCA_"
    return f"dnv2_NV_{pca}AB_wpca{pcs}_last.ckpt"


def _vlad_buff(name: str, nv_pca: int | None, num_pcs: int | None) -> tuple[str, TrainedVariant]:
    file = vlad_buff_file(nv_pca)
    return name, TrainedVariant(
        file,
        VLAD_BUFF_RELEASE + file,
        "Ahmedest61/VLAD-BuFF",
        {"nv_pca": nv_pca, "num_pcs": num_pcs},
    )


# ImageNet's per-channel mean and standard deviation (RGB, in 0..1 units): how the DINO
# family, torchvision's ImageNet weights and the trained VPR models normalise an image.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

# torchvision's IMAGENET1K_V1 ResNet weights, each named after the first 8 hex digits of
# its SHA-256: what ``pretrained=True`` gave the VPR models (MixVPR / BoQ ask for
# "IMAGENET1K_V1" by name) and what SNSM uses.
TORCHVISION_RESNET_URLS = {
    18: "https://download.pytorch.org/models/resnet18-f37072fd.pth",
    34: "https://download.pytorch.org/models/resnet34-b627a593.pth",
    50: "https://download.pytorch.org/models/resnet50-0676ba61.pth",
    101: "https://download.pytorch.org/models/resnet101-63fe2227.pth",
    152: "https://download.pytorch.org/models/resnet152-394f9c45.pth",
}


def _torchvision_resnet(depth: int) -> TrainedVariant:
    file = TORCHVISION_RESNET_URLS[depth].rpartition("/")[2]
    return TrainedVariant(
        file,
        TORCHVISION_RESNET_URLS[depth],
        "pytorch/vision",
        {"depth": depth},
        sha256=file.split("-")[1].split(".")[0],
    )


# The trained VPR models (docs/methods.md, "Trained models"): each model module reads its
# entry here (trained_model) for its files, URLs and input size.
_TRAINED_MODELS: dict[str, TrainedModel] = {
    # VGG16 conv5_3 + NetVLAD (+ whitening), Pittsburgh 30k; Patch-NetVLAD reads images
    # with PIL and resizes them to 640 x 480 with torchvision's Resize (antialiased).
    "netvlad": TrainedModel(
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
    # DINOv2-B/14 + NetVLAD with burst-aware weights + whitening PCA, evaluated at
    # 322 x 322 (PIL bilinear); each file also gives its VLAD before the whitening.
    "vlad_buff": TrainedModel(
        dict(
            _vlad_buff(name, nv_pca, pcs)
            for name, nv_pca, pcs in (
                ("dnv2_NV_AB_wpca8192", None, 8192),
                ("dnv2_NV_AB_vlad49152", None, None),
                ("dnv2_NV_192PCA_AB_wpca4096", 192, 4096),
                ("dnv2_NV_192PCA_AB_vlad12288", 192, None),
            )
        ),
        (322, 322),
        14,
        "DINOv2-B/14 patch tokens after the final LayerNorm, 768-d",
    ),
    # DINOv2-B/14 (no final norm) + Bag-of-Queries; BoQ's README reads with torchvision's
    # bicubic antialiased Resize on the float tensor.
    "boq_dinov2": TrainedModel(
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
        resize="bicubic_antialias",
    ),
    # DINOv2-B/14 + SALAD-style aggregation + linear projection, at the images' own size
    # (VPR-methods-evaluation resizes nothing by default; MegaLoc rounds each side to a
    # multiple of 14 itself, so no crop).
    "megaloc": TrainedModel(
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
        own_size=True,
    ),
    # ResNet-50 cut after layer3 + feature mixing (4096-d), GSV-Cities; 320 x 320 (its
    # mixer's 20 x 20 positions fix the input size).
    "mixvpr": TrainedModel(
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
    # ResNet-50 cut after layer3 + Bag-of-Queries, 16384-d, 384 x 384, read as BoQ-DINOv2.
    "boq_resnet50": TrainedModel(
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
        resize="bicubic_antialias",
    ),
    # ResNet trunk + GeM + FC, at the images' own size (their evaluation resizes
    # nothing); one variant per published backbone and length, ResNet50_2048 first.
    **{
        name.lower(): TrainedModel(
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
            own_size=True,
        )
        for name, published in (("CosPlace", _COSPLACE_DIMS), ("EigenPlaces", _EIGENPLACES_DIMS))
    },
    # torchvision's ImageNet ResNet-50 as dense features only: the map of `layer` 1-4
    # (SNSM's All-Backbones-VLAD baseline reads layer1-4, layer3 by default), at the
    # dataset's resolution as SNSM reads it.
    "resnet50": TrainedModel(
        {"imagenet1k_v1": _torchvision_resnet(50)},
        None,
        16,
        "the ImageNet ResNet-50's `layer` map (layer1-4: 256-2048-d, stride 4-32)",
        crop=False,
        layer_strides={1: 4, 2: 8, 3: 16, 4: 32},
        descriptor=False,
    ),
}


def trained_model(name: str) -> TrainedModel:
    """Trained kind ``name``'s entry, which its model module reads."""
    return _TRAINED_MODELS[name]


def _trained(name: str, spec: TrainedModel) -> ModelKind:
    """A trained model's backbone kind."""
    return ModelKind(
        name,
        "backbone",
        {
            "checkpoint": None,
            "variant": spec.default_variant,
            # A trunk has no descriptor of its own: its dense map.
            "output": TRAINED_OUTPUTS[0] if spec.descriptor else "features",
            **({"resolution": list(spec.input_size)} if spec.input_size else {}),
            **({"resolution": OWN_SIZE} if spec.own_size else {}),
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
        # 2: the grey image in float64, elementwise (skimage's rgb2gray is a float32
        # BLAS product whose rounding moved with the kernel), DAISY in float64.
        ModelKind(
            "daisy",
            "backbone",
            {"patch_size": 8, "radius": 12, "rings": 2, "histograms": 6, "orientations": 8},
            version=2,
        ),
        # AnyLoc / SegVLAD: value facet of block 31 (0-based) of ViT-G/14's 40.
        ModelKind(
            "dinov2",
            "backbone",
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
            {"model": "facebook/dino-vitb8", "layer": -1, **_VIT},
            weights="model",
            uses_gpu=True,
            spec=VitFamily({"vit": True}, pooler=False),
        ),
        ModelKind("import", "backbone", {"patch_size": 14}, weights="file"),
        *(_trained(name, spec) for name, spec in _TRAINED_MODELS.items()),
    )
}

# The trained models' backbone kinds, in registry order (the schema's x-kinds of the
# keys they read name this constant).
TRAINED_KINDS = tuple(n for n, k in BACKBONES.items() if isinstance(k.spec, TrainedModel))

SEGMENTERS: dict[str, ModelKind] = {
    kind.name: kind
    for kind in (
        # 2: the image's Lab conversion with its RGB -> XYZ product elementwise in
        # float64 (skimage's float32 BLAS product moved with the kernel).
        ModelKind(
            "slic",
            "segmenter",
            {"n_segments": 50, "compactness": 10.0, "sigma": 1.0},
            version=2,
        ),
        ModelKind(
            "felzenszwalb",
            "segmenter",
            {"scale": 100.0, "sigma": 0.8, "min_size": 50},
        ),
        # The original automatic mask generator's defaults (ViT-H).
        ModelKind(
            "sam",
            "segmenter",
            {"model": "facebook/sam-vit-huge", **_SAM_GENERATOR},
            weights="model",
            uses_gpu=True,
            spec=SamKind("SamModel"),
        ),
        # SAM-HQ's automatic mask generator (SAM's, defaults unchanged) on the HQ decoder:
        # one mask per point, best multimask logits + HQ logits (hq_token_only off).
        ModelKind(
            "sam_hq",
            "segmenter",
            {"model": "syscv-community/sam-hq-vit-huge", **_SAM_GENERATOR, "hq_token_only": False},
            weights="model",
            uses_gpu=True,
            spec=SamKind("SamHQModel", ("hq_token_only",)),
        ),
        # SAM 2's own automatic mask generator defaults (Hiera-L): pred_iou_thresh 0.8;
        # multimask output on and use_m2m off (fixed here).
        ModelKind(
            "sam2",
            "segmenter",
            {"model": "facebook/sam2.1-hiera-large", **_SAM_GENERATOR, "pred_iou_thresh": 0.8},
            weights="model",
            uses_gpu=True,
            spec=SamKind("Sam2Model"),
        ),
        ModelKind("import", "segmenter", weights="file"),
    )
}

# The config key that names an entry's kind, and the kinds of each stage that runs one.
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
