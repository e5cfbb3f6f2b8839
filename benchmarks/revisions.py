"""Code of an earlier commit beside today's, for a benchmark's "before" column.

``module_at(rev, name)`` executes ``src/<name as a path>.py`` of ``rev`` (``git show``) as
a module of its own. Its own imports are today's package, except the modules named in
``old``: those are served from ``rev`` too while it loads, for the modules that have
moved or gone since (``vprflow.core.registry``, the stage readers of ``stages/*.py``), so
an old file imports as it did at its commit. Not a ``bench_*`` script: the benchmarks
import it.
"""

from __future__ import annotations

import subprocess
import sys
import types
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def source_at(rev: str, path: str) -> str:
    """The text of ``path`` (relative to the repository) at ``rev``, or of the file
    ``rev`` names: a saved copy, for a machine the checkout reaches without git (a lent
    GPU: ``git show REV:PATH > FILE``)."""
    if Path(rev).is_file():
        return Path(rev).read_text()
    return subprocess.run(
        ["git", "show", f"{rev}:{path}"], cwd=REPO, capture_output=True, text=True, check=True
    ).stdout


def _path(name: str) -> str:
    return "src/" + name.replace(".", "/") + ".py"


def _execute(rev: str, name: str, as_name: str) -> types.ModuleType:
    module = types.ModuleType(as_name)
    sys.modules[as_name] = module  # dataclasses look their module up
    exec(compile(source_at(rev, _path(name)), f"{rev}:{_path(name)}", "exec"), module.__dict__)
    return module


@contextmanager
def modules_at(rev: str, old: tuple[str, ...]) -> Iterator[None]:
    """While inside, ``import <name>`` of each of ``old`` (in order: an earlier one may be
    imported by a later one) gives the module as it was at ``rev``."""
    saved = {name: sys.modules.get(name) for name in old}
    try:
        for name in old:
            sys.modules[name] = _execute(rev, name, name)
        yield
    finally:
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module


def module_at(rev: str, name: str, as_name: str, old: tuple[str, ...] = ()) -> types.ModuleType:
    """Module ``name`` (``vprflow.stages.descriptors``) at ``rev``, registered as
    ``as_name``, its imports of ``old`` served from ``rev`` as well."""
    with modules_at(rev, old):
        return _execute(rev, name, as_name)
