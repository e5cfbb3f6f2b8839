"""Which function loads each model kind of :mod:`vprflow.models.kinds`.

Each loader imports its model module when it runs, so that importing this module (as
planning and the stages do) imports no torch; the model modules read their kinds'
data from :mod:`vprflow.models.kinds`, never from here, so no import runs in a circle.
``tests/test_registry.py`` checks that every kind that loads a model has a loader here.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from vprflow.models.kinds import model_kind


def _load_daisy(params: dict, device: str = "auto"):
    from vprflow.models.backbones import load_daisy

    return load_daisy(params, device)


def _load_vit(params: dict, device: str = "auto"):
    from vprflow.models.vit import load_vit

    return load_vit(params, device)


def _load_slic(params: dict, device: str = "auto"):
    from vprflow.models.segmenters import load_slic

    return load_slic(params, device)


def _load_felzenszwalb(params: dict, device: str = "auto"):
    from vprflow.models.segmenters import load_felzenszwalb

    return load_felzenszwalb(params, device)


def _load_sam(params: dict, device: str = "auto"):
    from vprflow.models.sam.adapters import load_sam

    return load_sam(params, device)


# The trained models' own loaders, ``(checkpoint path, **variant loader_options) ->
# nn.Module`` (:class:`vprflow.models.kinds.TrainedModel`).


def _netvlad(checkpoint: str, **options):
    from vprflow.models.trained.netvlad import load_netvlad

    return load_netvlad(checkpoint, **options)


def _salad(checkpoint: str, **options):
    from vprflow.models.trained.salad import load_salad

    return load_salad(checkpoint, **options)


def _boq_dinov2(checkpoint: str, **options):
    from vprflow.models.trained.boq_dinov2 import load_boq_dinov2

    return load_boq_dinov2(checkpoint, **options)


def _vlad_buff(checkpoint: str, **options):
    from vprflow.models.trained.vlad_buff import load_vlad_buff

    return load_vlad_buff(checkpoint, **options)


def _megaloc(checkpoint: str, **options):
    from vprflow.models.trained.megaloc import load_megaloc

    return load_megaloc(checkpoint, **options)


def _mixvpr(checkpoint: str, **options):
    from vprflow.models.trained.mixvpr import load_mixvpr

    return load_mixvpr(checkpoint, **options)


def _convap(checkpoint: str, **options):
    from vprflow.models.trained.convap import load_convap

    return load_convap(checkpoint, **options)


def _boq_resnet50(checkpoint: str, **options):
    from vprflow.models.trained.boq import load_boq_resnet50

    return load_boq_resnet50(checkpoint, **options)


def _cosplace(checkpoint: str, **options):
    from vprflow.models.trained.cosplace import load_cosplace

    return load_cosplace(checkpoint, **options)


def _eigenplaces(checkpoint: str, **options):
    from vprflow.models.trained.cosplace import load_eigenplaces

    return load_eigenplaces(checkpoint, **options)


def _resnet50(checkpoint: str, **options):
    from vprflow.models.trunks.resnet import load_resnet

    return load_resnet(checkpoint, **options)


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
    from vprflow.models.trained.backbone import load_trained

    return load_trained(params, TRAINED_MODELS[params["backbone"]], device)


# Kind -> loader, ``(params, device) -> model``, per stage; ``import`` kinds read a file
# and load nothing.
LOADERS: dict[str, dict[str, Callable[..., Any]]] = {
    "features": {
        "daisy": _load_daisy,
        "dinov2": _load_vit,
        "dinov3": _load_vit,
        "dino": _load_vit,
        **dict.fromkeys(TRAINED_MODELS, _load_trained),
    },
    "segments": {
        "slic": _load_slic,
        "felzenszwalb": _load_felzenszwalb,
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
