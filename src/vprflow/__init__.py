"""vprflow: training-free visual place recognition experiments as a Snakemake workflow.

The package is in wings, one folder per concern, imports flowing one way (down this
list): ``core`` (arrays, files, paths, stores, errors, devices), ``data`` (images,
datasets, ground truth, presets, downloads), ``models`` (backbones and segmenters: their
kinds and loaders), ``aggregation`` (VLAD, SegVLAD, SNSM, pooling, PCA), ``search`` (k-NN,
voting), ``evaluation`` (recall, precision-recall, re-ranking, figures), ``planning``
(config, plan, fingerprints, reports) and ``stages`` (one module per rule).
docs/ARCHITECTURE.md reads them in the order a query takes.

Until release 0.3 the flat module paths of 0.1 (``vprflow.datasets``, ``vprflow.knn.exact``,
...) still import, as aliases of their new modules, with a ``DeprecationWarning``.
"""

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

# Old module -> its new place (release 0.2 moved the flat modules into wings).
MOVED = {
    **dict.fromkeys(("arrays", "files", "paths", "stores", "devices"), "core"),
    **dict.fromkeys(
        (
            "images",
            "datasets",
            "ground_truth",
            "positions",
            "published_truth",
            "published",
            "presets",
            "download",
        ),
        "data",
    ),
    **dict.fromkeys(("checkpoints", "vit", "backbones", "segmenters"), "models"),
    **dict.fromkeys(("vlad", "segvlad", "snsm", "pooling", "pca", "vocabularies"), "aggregation"),
    **dict.fromkeys(("voting",), "search"),
    **dict.fromkeys(("recall", "precision_recall", "rerank", "figures"), "evaluation"),
    **dict.fromkeys(
        ("config", "plan", "fingerprints", "reports", "reruns", "store_index"), "planning"
    ),
    "runner": "stages.runner",
    "knn": "search",
    **{f"knn.{m}": f"search.{m}" for m in ("exact", "approximate", "flat", "topk", "inputs")},
    **{f"sam_{m}": f"models.sam.{m}" for m in ("adapters", "decoder", "generator", "masks")},
}
MOVED = {old: new if "." in new or old == "knn" else f"{new}.{old}" for old, new in MOVED.items()}


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Imports ``vprflow.<old>`` as the module it moved to, with a warning."""

    def find_spec(self, fullname, path=None, target=None):
        old = fullname.removeprefix(__name__ + ".")
        if fullname.startswith(__name__ + ".") and old in MOVED:
            return importlib.util.spec_from_loader(fullname, self)
        return None

    def create_module(self, spec):
        old = spec.name.removeprefix(__name__ + ".")
        new = f"{__name__}.{MOVED[old]}"
        warnings.warn(
            f"{spec.name} moved to {new} (docs/ARCHITECTURE.md); the old path goes in 0.3",
            DeprecationWarning,
            stacklevel=2,
        )
        return importlib.import_module(new)

    def exec_module(self, module):
        pass  # the new module is already imported


if not any(isinstance(finder, _MovedModules) for finder in sys.meta_path):
    sys.meta_path.insert(0, _MovedModules())  # before the path finder: knn.flat too
