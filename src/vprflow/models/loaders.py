"""Which function loads each model kind of :mod:`vprflow.models.kinds`.

The model modules that import torch or transformers are named with
:func:`vprflow.core.lazy.lazy_import`: each is imported when its loader first runs, so
importing this module (as planning and the stages do) imports no torch. DAISY and the
superpixel segmenters import scikit-image the same way. The model modules read their
kinds' data from :mod:`vprflow.models.kinds`, never from here, so no import runs in a
circle. ``tests/planning/test_registry.py`` checks that every kind that loads a model has a
loader here.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from vprflow.core.lazy import lazy_import
from vprflow.models import backbones, segmenters
from vprflow.models.kinds import model_kind

vit = lazy_import("vprflow.models.vit")
sam = lazy_import("vprflow.models.sam.adapters")
trained = lazy_import("vprflow.models.trained.backbone")
netvlad = lazy_import("vprflow.models.trained.netvlad")
salad = lazy_import("vprflow.models.trained.salad")
boq_dinov2 = lazy_import("vprflow.models.trained.boq_dinov2")
vlad_buff = lazy_import("vprflow.models.trained.vlad_buff")
megaloc = lazy_import("vprflow.models.trained.megaloc")
mixvpr = lazy_import("vprflow.models.trained.mixvpr")
convap = lazy_import("vprflow.models.trained.convap")
boq = lazy_import("vprflow.models.trained.boq")
cosplace = lazy_import("vprflow.models.trained.cosplace")
resnet = lazy_import("vprflow.models.trunks.resnet")


def _load_vit(params: dict, device: str = "auto"):
    return vit.load_vit(params, device)


def _load_sam(params: dict, device: str = "auto"):
    return sam.load_sam(params, device)


# The trained models' own loaders, ``(checkpoint path, **variant loader_options) ->
# nn.Module`` (:class:`vprflow.models.kinds.TrainedModel`).


def _netvlad(checkpoint: str, **options):
    return netvlad.load_netvlad(checkpoint, **options)


def _salad(checkpoint: str, **options):
    return salad.load_salad(checkpoint, **options)


def _boq_dinov2(checkpoint: str, **options):
    return boq_dinov2.load_boq_dinov2(checkpoint, **options)


def _vlad_buff(checkpoint: str, **options):
    return vlad_buff.load_vlad_buff(checkpoint, **options)


def _megaloc(checkpoint: str, **options):
    return megaloc.load_megaloc(checkpoint, **options)


def _mixvpr(checkpoint: str, **options):
    return mixvpr.load_mixvpr(checkpoint, **options)


def _convap(checkpoint: str, **options):
    return convap.load_convap(checkpoint, **options)


def _boq_resnet50(checkpoint: str, **options):
    return boq.load_boq_resnet50(checkpoint, **options)


def _cosplace(checkpoint: str, **options):
    return cosplace.load_cosplace(checkpoint, **options)


def _eigenplaces(checkpoint: str, **options):
    return cosplace.load_eigenplaces(checkpoint, **options)


def _resnet50(checkpoint: str, **options):
    return resnet.load_resnet(checkpoint, **options)


# Trained kind -> its model's loader, which load_trained wraps into a backbone.
TRAINED_MODELS: dict[str, Callable[..., Any]] = {
    "netvlad": _netvlad,
    "salad": _salad,
    "boq_dinov2": _boq_dinov2,
    "vlad_buff": _vlad_buff,
    "megaloc": _megaloc,
    "mixvpr": _mixvpr,
    "convap": _convap,
    "boq_resnet50": _boq_resnet50,
    "cosplace": _cosplace,
    "eigenplaces": _eigenplaces,
    "resnet50": _resnet50,
}


def _load_trained(params: dict, device: str = "auto"):
    return trained.load_trained(params, TRAINED_MODELS[params["backbone"]], device)


# Kind -> loader, ``(params, device) -> model``, per stage; ``import`` kinds read a file
# and load nothing.
LOADERS: dict[str, dict[str, Callable[..., Any]]] = {
    "features": {
        "daisy": backbones.load_daisy,
        "dinov2": _load_vit,
        "dinov3": _load_vit,
        "dino": _load_vit,
        **dict.fromkeys(TRAINED_MODELS, _load_trained),
    },
    "segments": {
        "slic": segmenters.load_slic,
        "felzenszwalb": segmenters.load_felzenszwalb,
        "sam": _load_sam,
        "sam_hq": _load_sam,
        "sam2": _load_sam,
    },
}


def load_model(stage: str, params: dict, device: str = "auto"):
    """The model of a backbone entry (``stage="features"``) or segmenter entry
    (``stage="segments"``), its kind's defaults filled in by its loader."""
    kind = model_kind(stage, params)
    if kind.reads_file:
        raise ValueError(f"{kind.role} {kind.name!r} reads a file; it has no model to load")
    return LOADERS[stage][kind.name](params, device)
