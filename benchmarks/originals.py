"""The original repositories the check_*.py scripts run beside vprflow: each is a folder
(extracted with ``git archive``, say) with an optional ``COMMIT`` file naming repository
and commit."""

from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path


def load_module(path: Path, name: str) -> types.ModuleType:
    """The original's source file ``path`` imported as module ``name`` (registered in
    ``sys.modules``, so that its own imports of ``name`` find it)."""
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def commit_of(folder: Path) -> str:
    """What the folder's ``COMMIT`` file says, or that the commit is unknown."""
    stamp = folder / "COMMIT"
    return stamp.read_text().strip() if stamp.is_file() else f"{folder.name} (commit unknown)"
