"""The trained models' published checkpoints a plan reads: which are missing, the one
message that names them all, and how the ``trained_checkpoint`` rule fetches them.

Planning hashes every checkpoint into its features key, so a missing file stops the
plan. :func:`vprflow.planning.plan.build_plan` collects every missing one first and
raises one :class:`~vprflow.core.errors.PlanError` naming each (file, config key,
variant, repository, URL, what is known of its SHA-256) and the command that fetches
them: ``snakemake trained_checkpoints`` with the run's config files. That command plans
with the missing files allowed (:func:`fetching_checkpoints`; their stages get no key
anyone may build) and runs one ``trained_checkpoint`` job per missing file, which
downloads to a temporary file beside it and renames it into place only after its
SHA-256 matched the published one (:func:`fetch_checkpoint`). A file served only from a
web page (Google Drive) is left to the user: the message and the fetch say where.
"""

from __future__ import annotations

import logging
import os
import re
import shlex
from dataclasses import dataclass
from pathlib import Path

from vprflow.core.files import atomic_path
from vprflow.data.download import DownloadError, fetch
from vprflow.models.kinds import TrainedVariant

log = logging.getLogger("vprflow")

# The target that fetches every missing checkpoint (workflow/rules/download.smk).
FETCH_TARGET = "trained_checkpoints"
# An offline mirror of the published files, by file name, may stand in for the
# publishers (tests; a cluster without internet): it serves every file, hand-downloaded
# ones included.
URL_ENV = "VPRFLOW_CHECKPOINT_URL"
# The fetch rule's output for a checkpoint the config names by an absolute path (the
# wildcard holds the rest; its log goes under logs/, which a leading "/" would leave).
ABSOLUTE_OUTPUT = "/{checkpoint}"


@dataclass(frozen=True)
class PlannedCheckpoint:
    """A checkpoint file a plan reads: where the config names it and what it should be."""

    path: str
    where: str  # the config key, "backbones.<entry>.checkpoint"
    kind: str
    variant: str
    published: TrainedVariant


def checkpoint_url(published: TrainedVariant) -> str | None:
    """Where ``published`` is fetched from: the mirror (``$VPRFLOW_CHECKPOINT_URL``) when
    set, else its URL when that serves the file; None for a page to download by hand."""
    mirror = os.environ.get(URL_ENV)
    if mirror:
        return f"{mirror.rstrip('/')}/{published.file}"
    return published.url if published.direct else None


def fetching_checkpoints(targets) -> bool:
    """Whether a ``snakemake`` command's targets (:func:`vprflow.planning.invocation.asked`) hold
    the fetch target, so that the plan may be built while checkpoints are missing."""
    return FETCH_TARGET in targets


def fetch_command(configfiles=()) -> str:
    """The command that fetches every missing checkpoint, with the run's config files
    (relative to the working directory where they are under it)."""
    names = []
    for file in configfiles:
        path = Path(file)
        try:
            name = str(path.resolve().relative_to(Path.cwd().resolve()))
        except ValueError:
            name = str(path)
        if name not in names:  # Snakemake lists the default config file again
            names.append(name)
    files = f" --configfile {' '.join(names)}" if names else ""
    return f"snakemake --cores 2 {FETCH_TARGET}{files}"


def absent(path: str) -> bool:
    """Whether the checkpoint at ``path`` is still to be put there: missing, or empty (0
    bytes: an interrupted copy, a ``touch``; no checkpoint is), which planning would hash
    into a key and the features job fail to read."""
    return not os.path.exists(path) or _empty(path)


def _empty(path: str) -> bool:
    return os.path.isfile(path) and os.path.getsize(path) == 0


def _sha256_text(published: TrainedVariant) -> str:
    if published.sha256 is None:
        return "no published SHA-256 on record"
    if len(published.sha256) < 64:
        return f"SHA-256 begins {published.sha256} (its file name)"
    return f"SHA-256 {published.sha256}"


def describe(checkpoint: PlannedCheckpoint) -> str:
    """One line on a checkpoint: the file (and that it is empty, where it is), its config
    key, the variant, who publishes it, where from, what is known of its hash."""
    published = checkpoint.published
    url = checkpoint_url(published)
    renamed = "" if Path(checkpoint.path).name == published.file else f" {published.file}"
    how = url if url else f"by hand, from the page {published.url}"
    empty = "empty: 0 bytes, an interrupted download or copy?; " if _empty(checkpoint.path) else ""
    return (
        f"{checkpoint.path} ({empty}{checkpoint.where}; {checkpoint.kind} variant "
        f"{checkpoint.variant!r}, {published.repository}{renamed}): {how}; "
        f"{_sha256_text(published)}"
    )


def missing_message(missing: list[PlannedCheckpoint], configfiles=()) -> str:
    """The error for every missing (or empty: :func:`absent`) checkpoint of a plan, with
    the command that fetches them and the files that command cannot fetch."""
    empty = [c.path for c in missing if _empty(c.path)]
    if not empty:
        state = "are missing"
    elif len(empty) == len(missing):
        state = "are empty"
    else:
        state = "are missing or empty"
    lines = [f"{len(missing)} trained-model checkpoint file(s) the plan reads {state}:"]
    lines += [f"  {describe(c)}" for c in missing]
    fetchable = [c for c in missing if checkpoint_url(c.published)]
    if fetchable:
        which = "them all" if len(fetchable) == len(missing) else f"the {len(fetchable)} with a URL"
        # Snakemake fetches no file that exists, an empty one included.
        remove = [shlex.quote(c.path) for c in fetchable if c.path in empty]
        first = f"rm {' '.join(remove)} && " if remove else ""
        lines.append(
            f"Fetch {which} (each kept only if its SHA-256 matches, where one is published) "
            f"with:\n  {first}{fetch_command(configfiles)}"
        )
    if len(fetchable) < len(missing):
        lines.append(
            f"The {len(missing) - len(fetchable)} marked 'by hand' are served from a web "
            "page: download each and put it at its path."
        )
    return "\n".join(lines)


def fetchable_paths(
    checkpoints: dict[str, PlannedCheckpoint], absolute: bool | None = None
) -> list[str]:
    """The checkpoint paths the ``trained_checkpoint`` rules can fetch: all, or only the
    absolute (``absolute=True``) or relative ones."""
    return sorted(
        p
        for p, c in checkpoints.items()
        if checkpoint_url(c.published) and absolute in (None, os.path.isabs(p))
    )


def by_hand(checkpoints: dict[str, PlannedCheckpoint]) -> list[str]:
    """What to say of each missing checkpoint the fetch cannot download."""
    return [
        f"{describe(c)}: not fetched, put it there yourself"
        for p, c in sorted(checkpoints.items())
        if not checkpoint_url(c.published) and absent(p)
    ]


def output_pattern(paths: list[str]) -> str:
    """A wildcard constraint matching exactly ``paths`` (nothing when there are none)."""
    return "|".join(re.escape(p) for p in paths) or "(?!)"


def fetch_checkpoint(url: str, sha256: str | None, out: str | Path) -> None:
    """Fetch ``url`` to ``out``, checking its SHA-256 (or the published first digits of
    it) when ``sha256`` is given; a mismatch leaves nothing at ``out`` and names both."""
    with atomic_path(out) as partial:
        actual = fetch(url, partial)
        size = partial.stat().st_size
        if sha256 is not None and not actual.startswith(sha256.lower()):
            raise DownloadError(
                f"checksum mismatch for {url}: expected sha256 {sha256.lower()}"
                f"{'...' if len(sha256) < 64 else ''}, got {actual} ({size} bytes); "
                f"{out} was not written"
            )
    checked = "matches the published one" if sha256 else "none is published to check it against"
    log.info("%s: %d bytes, sha256 %s (%s)", out, size, actual, checked)
