"""Every aggregator vprflow knows, one :class:`Aggregator` entry each: what it needs
upstream, what it outputs, its settings and its per-image function.

Each entry's ``compute`` is a function of this module, ``(grid [h, w, D], options,
**inputs) -> [dim]`` (``[S, dim]`` per segment), over the math of this wing;
:func:`vprflow.stages.image_descriptors.image_descriptor` reads the inputs the entry's
``needs`` name from their stores and runs it on every image, for every aggregator alike.
``options`` are the descriptor stage's params (the entry's ``options(method)`` and
``aggregator``). Torch-free: planning reads this module.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from vprflow.aggregation import pooling
from vprflow.aggregation.segvlad import image_segvlad, mask_patch_membership
from vprflow.aggregation.snsm import normalize_tokens, snsm_descriptor
from vprflow.aggregation.vlad import normalize_patches, vlad
from vprflow.core.arrays import l2_normalize

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

    ``vocabulary_input(method)``: for an aggregator that normalises each image's tokens
    before VLAD, the vocabulary stage's extra params that make its k-means see the
    patches the same way (``{"normalization": ...}``, :func:`normalize_tokens`); None:
    the stored patches as they are.

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
    vocabulary_input: Callable[[dict], dict] | None = None

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


# ------------------------------------------------------------------ per-image functions


def vlad_input(grid: np.ndarray, options: dict) -> np.ndarray:
    """Patches as VLAD sees them: L2-normalised per patch unless the method says not
    (AnyLoc's VLAD ``norm_descs=True``; stored float16 features are only nearly unit),
    in torch on the authors' layout, as their code normalises them before assigning."""
    if not options["normalize_descriptors"]:
        return grid
    return normalize_patches(grid.reshape(-1, grid.shape[-1])).reshape(grid.shape)


def segvlad_descriptors(
    grid: np.ndarray,
    options: dict,
    *,
    masks: np.ndarray,
    centres: np.ndarray,
    image_size: tuple[int, int],
    patch_size: int,
) -> np.ndarray:
    """SegVLAD: one VLAD vector per segment neighbourhood of ``options["order"]``
    (docs/methods.md §5), ``[S, K * D]``."""
    return image_segvlad(
        vlad_input(grid, options),
        masks,
        centres,
        image_size,
        patch_size,
        options["order"],
        crop_aligned=options["mask_to_patch"] == "crop_aligned",
        small_graph=options["small_graph"],
    )


def segment_gem_descriptors(
    grid: np.ndarray,
    options: dict,
    *,
    masks: np.ndarray,
    image_size: tuple[int, int],
    patch_size: int,
) -> np.ndarray:
    """Per-segment GeM: each segment's patches (the published mask-to-patch mapping,
    no neighbourhood) GeM-pooled after the pooling section's token normalisation, each
    row L2-normalised for the segment search, ``[S, D]``. SegVLAD's segment path with
    the simplest aggregation: a baseline for what VLAD and neighbourhoods add."""
    h, w, _ = grid.shape
    membership = mask_patch_membership(masks, image_size, (h, w), patch_size)
    tokens = normalize_tokens(grid, options["normalization"])
    pooled = pooling.segment_gem(tokens, membership, options["p"]).astype(np.float64)
    return l2_normalize(pooled).astype(np.float32)


def anyloc_vlad_descriptor(grid: np.ndarray, options: dict, *, centres: np.ndarray) -> np.ndarray:
    """AnyLoc VLAD of the whole patch grid (docs/methods.md §4), ``[K * D]``."""
    grid = vlad_input(grid, options)
    return vlad(grid.reshape(-1, grid.shape[-1]), centres)


def vlad_descriptor(grid: np.ndarray, options: dict, *, centres: np.ndarray) -> np.ndarray:
    """VLAD of the pooling baselines' normalised tokens (docs/methods.md §7), ``[K * D]``:
    SNSM's ``--vlad`` baseline normalises the backbone's tokens as its GeM / average /
    max do, then runs AnyLoc's VLAD, which L2-normalises each patch again."""
    tokens = normalize_tokens(grid, options["normalization"])
    return anyloc_vlad_descriptor(tokens, options, centres=centres)


_SNSM_KEYS = ("upscale", "window", "neighbourhood", "similarity", "normalization")


def snsm_image_descriptor(grid: np.ndarray, options: dict) -> np.ndarray:
    """SNSM support-map descriptor (docs/methods.md §6)."""
    return snsm_descriptor(grid, **{k: options[k] for k in _SNSM_KEYS})


# GeM / average / max pooling of the channel-normalised tokens (docs/methods.md §7): the
# SNSM authors pool tokens normalised like SNSM's own input.


def gem_descriptor(grid: np.ndarray, options: dict) -> np.ndarray:
    return pooling.gem(normalize_tokens(grid, options["normalization"]), p=options["p"])


def average_descriptor(grid: np.ndarray, options: dict) -> np.ndarray:
    return pooling.average_pool(normalize_tokens(grid, options["normalization"]))


def max_descriptor(grid: np.ndarray, options: dict) -> np.ndarray:
    return pooling.max_pool(normalize_tokens(grid, options["normalization"]))


def model_descriptor(grid: np.ndarray, options: dict) -> np.ndarray:
    """A trained model's own descriptor (docs/methods.md, "Trained models"): the 1 x 1
    grid its backbone entry stores under ``output: descriptor``, ``[D]``, L2-normalised
    again in float64 (the models normalise it; a float16 store rounds the norm)."""
    return l2_normalize(grid.reshape(-1).astype(np.float64)).astype(np.float32)


# ------------------------------------------------------------------ settings


def _segvlad_pca_fit(method: dict, options: dict) -> dict:
    """Published: one PCA per neighbourhood order, fitted on descriptors of the method's
    own order; an integer ``pca.fit_order`` fixes the order instead."""
    fit_order = method["pca"]["fit_order"]
    order = options["order"] if fit_order == "method" else fit_order
    return {**{k: v for k, v in options.items() if k != "store_dtype"}, "order": order}


def _segvlad_options(method: dict) -> dict:
    segvlad = method["segvlad"]
    return {
        "order": segvlad["order"],
        "mask_to_patch": segvlad["mask_to_patch"],
        "small_graph": segvlad["small_graph"],
        "store_dtype": segvlad["store_dtype"],
        **method["vlad"],
    }


def _pooling(name: str, compute) -> Aggregator:
    """GeM, average or max pooling: the `pooling` settings it uses (``gem_p`` for GeM
    only, passed to the pooling function as ``p``) are its options and its columns."""
    keys = ("normalization", "gem_p") if name == "gem" else ("normalization",)
    return Aggregator(
        name,
        (),
        "global",
        compute,
        lambda m: {"p" if k == "gem_p" else k: m["pooling"][k] for k in keys},
        lambda m: prefixed("pooling", {k: m["pooling"][k] for k in keys}),
        resize="antialias",
        exif_orientation="ignore",
        sections=("pooling",),
    )


AGGREGATORS: dict[str, Aggregator] = {
    agg.name: agg
    for agg in (
        Aggregator(
            "segvlad",
            ("segments", "vocabulary", "pca"),
            "segments",
            segvlad_descriptors,
            _segvlad_options,
            explanation="segment_matches",
            pca_fit=_segvlad_pca_fit,
            sections=("segvlad", "vlad"),
        ),
        Aggregator(
            "segment_gem",
            ("segments", "pca"),
            "segments",
            segment_gem_descriptors,
            lambda m: {"p": m["pooling"]["gem_p"], "normalization": m["pooling"]["normalization"]},
            lambda m: prefixed("pooling", {k: m["pooling"][k] for k in ("gem_p", "normalization")}),
            explanation="segment_matches",
            sections=("pooling",),
        ),
        Aggregator(
            "anyloc_vlad",
            ("vocabulary",),
            "global",
            anyloc_vlad_descriptor,
            sections=("vlad",),
        ),
        Aggregator(
            "snsm",
            (),
            "global",
            snsm_image_descriptor,
            explanation="support_maps",
            resize="antialias",
            exif_orientation="ignore",
            sections=("snsm",),
        ),
        # SNSM's All-Backbones-VLAD `--vlad` baseline: read and normalised as its pooling
        # baselines, the vocabulary fitted on the tokens so normalised.
        Aggregator(
            "vlad",
            ("vocabulary",),
            "global",
            vlad_descriptor,
            lambda m: {"normalization": m["pooling"]["normalization"], **m["vlad"]},
            lambda m: {
                **prefixed("pooling", {"normalization": m["pooling"]["normalization"]}),
                **prefixed("vlad", m["vlad"]),
            },
            resize="antialias",
            exif_orientation="ignore",
            sections=("pooling", "vlad"),
            vocabulary_input=lambda m: {"normalization": m["pooling"]["normalization"]},
        ),
        _pooling("gem", gem_descriptor),
        _pooling("average", average_descriptor),
        _pooling("max", max_descriptor),
        # A trained model's own descriptor: the 1 x 1 grid its backbone entry stores under
        # `output: descriptor`. Every published reader (Patch-NetVLAD, SALAD, BoQ,
        # VPR-methods-evaluation) opens images with PIL, ignoring EXIF orientation.
        Aggregator(
            "model",
            (),
            "global",
            model_descriptor,
            exif_orientation="ignore",
            reads="descriptor",
        ),
    )
}


def aggregator(name: str) -> Aggregator:
    if name not in AGGREGATORS:
        raise ValueError(f"unknown aggregator {name!r}; expected one of {sorted(AGGREGATORS)}")
    return AGGREGATORS[name]
