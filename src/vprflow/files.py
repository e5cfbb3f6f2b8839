"""Files written whole: to a temporary name beside the target, then renamed into place,
so an interrupted or concurrent job never leaves a complete-looking half file."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path


@contextmanager
def atomic_path(path: str | Path, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path to write ``path``'s content to; on success it replaces
    ``path``, on failure it is removed. ``suffix`` ends the temporary name (for writers
    that insist on one, e.g. ``np.savez`` and ``.npz``). Parent folders are created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # The process id keeps two jobs writing the same file from sharing a temporary.
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp{suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` via :func:`atomic_path`."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)
