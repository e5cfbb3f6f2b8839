"""Modules imported when first used: :func:`lazy_import`, the package's one way of
deferring an import.

A job imports only the libraries it computes with (torch costs ~1.2 s a process, faiss,
cv2 and scikit-image a tenth of that each; ``tests/stages/test_job_imports.py``), and planning
never imports torch. docs/ARCHITECTURE.md's import rule says which modules name a
library at their top as ``name = lazy_import("module")``: the module is imported the
first time one of its attributes is read. A name set on the stand-in stays there, so
code that replaces a module's attribute imports the module itself. ``scripts/import_graph.py``
reads ``lazy_import("vprflow.x.y")`` as an import of ``vprflow.x.y``, so the graph still
shows every tie.

The stand-in is not put in ``sys.modules`` (as ``importlib.util.LazyLoader``'s module
would be): there, a name means the module was imported, which the tests of the jobs'
imports read.
"""

from __future__ import annotations

import importlib
import types


class LazyModule(types.ModuleType):
    """Stands for module ``__name__`` until one of its attributes is read; then imports
    it and answers every read from the module itself. Nothing is copied, so a name the
    module rebinds later (a test's monkeypatch, a module-level cache) reads as it is
    there now."""

    def __getattr__(self, attribute: str):
        return getattr(importlib.import_module(self.__name__), attribute)


def lazy_import(name: str) -> types.ModuleType:
    """Module ``name`` (dotted, e.g. ``"matplotlib.pyplot"``), imported when one of its
    attributes is first read; an error of the import is raised there."""
    return LazyModule(name)
