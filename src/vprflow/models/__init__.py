"""Models that see images: where weights come from (``hub``, ``checkpoints``), the
dense-feature backbones (``vit``, ``backbones``) and the segmenters (``segmenters``,
the Segment Anything family in ``sam``).
"""

import importlib
import warnings


def __getattr__(name):
    # vprflow.models was the module now called vprflow.models.hub (moved in 0.2).
    if name.startswith("_") or name in {
        "hub",
        "vit",
        "backbones",
        "segmenters",
        "checkpoints",
        "sam",
    }:
        raise AttributeError(f"module 'vprflow.models' has no attribute {name!r}")
    hub = importlib.import_module("vprflow.models.hub")
    if not hasattr(hub, name):
        raise AttributeError(f"module 'vprflow.models' has no attribute {name!r}")
    warnings.warn(
        f"vprflow.models.{name} moved to vprflow.models.hub.{name}; the old path goes in 0.3",
        DeprecationWarning,
        stacklevel=2,
    )
    return getattr(hub, name)
