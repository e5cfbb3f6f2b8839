"""Files written whole: to a temporary name beside the target, then renamed into place,
so an interrupted or concurrent job never leaves a complete-looking half file.

Temporary names carry a **writer tag** (:func:`writer_tag`: host, process id and a
random token), so two runs writing the same target at once (``snakemake --nolock``)
never share a temporary, and a leftover can be told apart from a live writer's
(:func:`is_abandoned`): on this host, its process is gone; written from another host,
nothing in it changed for :data:`ABANDONED_AFTER_S`.
"""

from __future__ import annotations

import errno
import os
import re
import secrets
import socket
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from vprflow.core.errors import PlanError

# A temporary written on another host (a shared file system under a cluster) counts as
# abandoned once nothing in it changed for this long: its process cannot be asked.
ABANDONED_AFTER_S = 24 * 3600
TAG = r"(?P<host>[A-Za-z0-9_-]+)-(?P<pid>[0-9]+)-(?P<token>[0-9a-f]{8})"


def host_name() -> str:
    """This host's name, reduced to the characters a writer tag allows."""
    return re.sub(r"[^A-Za-z0-9_-]", "_", socket.gethostname()) or "host"


def writer_tag() -> str:
    """``<host>-<pid>-<random>``: unique to one writer, parsed back by :data:`TAG`."""
    return f"{host_name()}-{os.getpid()}-{secrets.token_hex(4)}"


def process_alive(pid: int) -> bool:
    """Whether process ``pid`` exists on this host (one owned by another user counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def newest_change(path: Path) -> float:
    """The newest modification time of ``path`` and the folders under it (a file
    created or renamed in a folder changes the folder's time)."""
    newest = path.lstat().st_mtime
    if path.is_dir() and not path.is_symlink():
        for root, folders, _ in os.walk(path):
            for name in folders:
                try:
                    newest = max(newest, os.lstat(os.path.join(root, name)).st_mtime)
                except FileNotFoundError:
                    pass
    return newest


def is_abandoned(path: Path, host: str, pid: int, max_age_s: float = ABANDONED_AFTER_S) -> bool:
    """Whether the temporary ``path`` written by process ``pid`` on ``host`` has no live
    writer: on this host, the process is gone; on another, nothing in it changed for
    ``max_age_s`` seconds."""
    if host == host_name():
        return pid != os.getpid() and not process_alive(pid)
    try:
        return time.time() - newest_change(path) > max_age_s
    except FileNotFoundError:
        return False


@contextmanager
def atomic_path(path: str | Path, suffix: str = "") -> Iterator[Path]:
    """Yield a temporary path to write ``path``'s content to; on success it replaces
    ``path``, on failure it is removed. ``suffix`` ends the temporary name (for writers
    that insist on one, e.g. ``np.savez`` and ``.npz``). Parent folders are created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # The writer tag keeps two jobs writing the same file from sharing a temporary.
    tmp = path.with_name(f".{path.name}.{writer_tag()}.tmp{suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` via :func:`atomic_path`."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def link_loop(path: str | Path, shown: int = 8) -> str | None:
    """Where following the links from ``path`` goes round (``a.jpg -> b.jpg -> a.jpg``:
    its name, then each link's target as written) when it never reaches a file (``ELOOP``),
    for an error naming the loop; None when ``path`` does not loop."""
    try:
        os.stat(path)
        return None
    except OSError as error:
        if error.errno != errno.ELOOP:
            return None
    chain, seen, current = [os.path.basename(path)], set(), os.path.abspath(path)
    while current not in seen:
        if len(chain) > shown:
            chain.append("...")
            break
        seen.add(current)
        try:
            target = os.readlink(current)
        except OSError:  # a folder on the way loops, not a link named here
            break
        chain.append(target)
        current = os.path.normpath(os.path.join(os.path.dirname(current), target))
    return " -> ".join(chain)


def check_writable(folder: str | Path) -> None:
    """Raise :class:`PlanError` naming ``folder`` unless a file can be created in it (or,
    while it is missing, in the folder it would be made in; nothing is left behind).
    Planning writes there before any job runs, even for a dry run (the content-hash memo,
    the store index, the tables' marks), and a read-only file system or a folder of
    another user's otherwise stops it with a bare ``OSError``. A file is really created:
    ``os.access`` answers yes to root over any mode bits."""
    folder = Path(folder)
    where = folder.absolute()
    while not where.is_dir() and where.parent != where:
        where = where.parent
    probe = where / f".write-probe.{writer_tag()}.tmp"
    try:
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
        os.unlink(probe)
    except OSError as error:
        why = error.strerror or str(error)
        remedy = {
            errno.EROFS: "remount it read-write, or ",
            errno.EACCES: "give this user write permission on it (chmod, chown), or ",
            errno.EPERM: "give this user write permission on it (chmod, chown), or ",
        }.get(error.errno, "")
        made = "" if where == folder.absolute() else f" (where {folder.name}/ is to be made)"
        raise PlanError(
            f"{where}{made}: cannot write there ({why}). vprflow writes in {folder.name}/ from "
            "planning on, a dry run too (the content-hash cache, the store index): "
            f"{remedy}run from a copy of this working folder where you can write "
            "(copy results/ along to keep what is built)"
        ) from None
