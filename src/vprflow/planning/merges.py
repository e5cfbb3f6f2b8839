"""Datasets that more than one config file defines, as Snakemake merges them.

Snakemake reads its config files in order (the workflow's ``configfile:`` first, then
each ``--configfile``) and merges each over the ones before, key by key, dictionaries
recursively. A dataset of one's own that reuses a name an earlier file defines (the
shipped ``corridor``) is therefore not an entry of its own: it is one entry made of
both files' keys, with the earlier file's ``rerank``, ``recall_at`` or ``download``
where the later file does not give them. :func:`dataset_merges` reads the files again
and says, for each such dataset, which file gave which key; a ``download`` stays only
where it still names the folder its file gave (:func:`without_foreign_downloads`), so an
archive is never unpacked into a folder that another file named for its own images.

An entry that only adjusts another file's dataset (config/trained.yaml's ``corridor``:
its methods and re-rankers; the `.test` config's, restating its folders) is what merging
is for and goes unremarked: a note is for a later file that names other images (a key of
:data:`FOLDER_KEYS` with another value).
"""

from __future__ import annotations

import copy
import os
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import yaml

# The keys that say where a dataset's images are: a file that gives one describes
# images of its own, not an adjustment of another file's dataset.
FOLDER_KEYS = ("path", "reference", "query")


def merge_order(configfiles: Sequence, command_line: Sequence) -> list[str]:
    """The config files in the order Snakemake merges them: the workflow's own
    (``workflow.configfiles`` holds them after the command line's) that the command line
    does not name again, then the command line's ``--configfile`` in its order."""
    named = {os.path.realpath(path) for path in command_line}
    own = [str(p) for p in configfiles if os.path.realpath(p) not in named]
    return own + [str(path) for path in command_line]


@dataclass(frozen=True)
class DatasetMerge:
    """One dataset that several config files define, and what each gave."""

    name: str
    files: tuple[str, ...]  # the files that define it, in merge order
    # Each file's keys of the merged entry (the last file to give a key has it); a key
    # whose value several files shaped is named by its sub-keys (`ground_truth.file`).
    keys: dict[str, tuple[str, ...]]
    # The folder the merged entry reads and the file that gave it.
    folder: str
    folder_file: str
    # The file whose `download` lays out another folder than ``folder``, if any, and
    # the keys of that file left out with it (its `download`, the `source` it names).
    foreign_download: str | None = None
    left_out: tuple[str, ...] = ()

    def note(self) -> str:
        """What a user reads: the files, the keys from each, and what to do."""
        files = " and ".join(self.files)
        given = "; ".join(
            f"from {file}: {', '.join(keys)}" for file, keys in self.keys.items() if keys
        )
        text = (
            f"dataset {self.name!r} is defined in {files}: Snakemake merges later config "
            f"files over earlier ones, so it is one entry ({given}). If it is a dataset "
            "of your own, give it a name of its own"
        )
        if self.foreign_download:
            text += (
                f". {self.foreign_download}'s `download` lays out its own folder, not "
                f"{self.folder_file}'s {self.folder!r}: {' and '.join(self.left_out)} "
                f"left out, and nothing is downloaded into {self.folder!r}"
            )
        return text


def dataset_merges(files: Iterable[str | Path]) -> list[DatasetMerge]:
    """The datasets that two or more of ``files`` (config files, in merge order:
    :func:`merge_order`) define where a file after the first that defines one gives a
    :data:`FOLDER_KEYS` value other than the earlier files' (:func:`_names_other_images`),
    by name. Files that cannot be read are skipped (Snakemake reports its own errors)."""
    entries: dict[str, list[tuple[str, dict]]] = {}
    seen: dict[str, str] = {}
    for path in files:
        real = os.path.realpath(path)
        try:
            loaded = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, yaml.YAMLError):
            continue
        shown = seen.setdefault(real, _shown(path))
        datasets = loaded.get("datasets") if isinstance(loaded, dict) else None
        for name, entry in (datasets if isinstance(datasets, dict) else {}).items():
            if isinstance(entry, dict):
                entries.setdefault(name, []).append((shown, entry))
    merges = []
    for name, given in sorted(entries.items()):
        files_in_order = tuple(dict.fromkeys(file for file, _ in given))
        first = files_in_order[0]
        if len(files_in_order) < 2 or not _names_other_images(given, first):
            continue
        merged: dict = {}
        origin: dict = {}
        for file, entry in given:
            _merge(merged, origin, entry, file)
        keys = {file: tuple(_keys_of(origin, file)) for file in files_in_order}
        folder_file = origin.get("path") if isinstance(origin.get("path"), str) else first
        download_file = _origin_file(origin.get("download"))
        foreign, left_out = None, ()
        if download_file is not None and download_file != folder_file:
            own = next(e for f, e in reversed(given) if f == download_file and "download" in e)
            if "path" in own and own["path"] != merged.get("path"):
                foreign = download_file
                left_out = tuple(
                    key
                    for key in ("download", "source")
                    if key in origin and _origin_file(origin[key]) == foreign
                )
        merges.append(
            DatasetMerge(
                name,
                files_in_order,
                keys,
                str(merged.get("path")),
                folder_file,
                foreign,
                left_out,
            )
        )
    return merges


def _names_other_images(given: list[tuple[str, dict]], first: str) -> bool:
    """Whether a file after ``first`` gives a :data:`FOLDER_KEYS` value other than the
    one the files before it gave: other images under the same name. A file restating the
    same folders (the `.test` config's corridor, at another resolution) adjusts the same
    dataset, as config/trained.yaml does."""
    before: dict = {}
    for file, entry in given:
        for key in FOLDER_KEYS:
            if key in entry:
                if file != first and entry[key] != before.get(key):
                    return True
                before[key] = entry[key]
    return False


def without_foreign_downloads(config: dict, merges: Iterable[DatasetMerge]) -> dict:
    """``config`` without the ``download`` (and the ``source`` that came with it) of each
    merged dataset whose download lays out another folder than the one the entry reads
    (the caller's config stays as given)."""
    foreign = {m.name: m.left_out for m in merges if m.foreign_download}
    datasets = config.get("datasets")
    if not foreign or not isinstance(datasets, dict):
        return config
    datasets = dict(datasets)
    for name, left_out in foreign.items():
        if isinstance(datasets.get(name), dict):
            datasets[name] = {
                k: copy.deepcopy(v) for k, v in datasets[name].items() if k not in left_out
            }
    return {**config, "datasets": datasets}


_SAID: set[str] = set()


def say_merges(merges: Iterable[DatasetMerge]) -> None:
    """Print each merge's note once per process (the log of the run that plans)."""
    for merge in merges:
        note = merge.note()
        if note not in _SAID:
            _SAID.add(note)
            print(f"vprflow: {note}", file=sys.stderr)


def _shown(path: str | Path) -> str:
    """A file's name for a message: relative to the working directory when under it."""
    relative = os.path.relpath(os.path.realpath(path))
    return relative if not relative.startswith("..") else str(path)


def _merge(merged: dict, origin: dict, entry: dict, file: str) -> None:
    """Merge ``entry`` over ``merged`` as Snakemake's ``update_config`` does, recording
    in ``origin`` (the same shape) which file gave each value."""
    for key, value in entry.items():
        if isinstance(value, dict):
            if not isinstance(merged.get(key), dict):
                merged[key], origin[key] = {}, {}
            _merge(merged[key], origin[key], value, file)
        else:
            merged[key], origin[key] = value, file


def _files_in(origin) -> set[str]:
    if isinstance(origin, dict):
        return set().union(*map(_files_in, origin.values())) if origin else set()
    return {origin}


def _origin_file(origin) -> str | None:
    """The one file a value came from (the last to give its first leaf when several)."""
    if origin is None or isinstance(origin, str):
        return origin
    files = _files_in(origin)
    return next(iter(files)) if len(files) == 1 else _origin_file(next(iter(origin.values())))


def _keys_of(origin: dict, file: str, prefix: str = "") -> list[str]:
    """The keys (dotted where a value's sub-keys came from several files) of ``file``."""
    keys = []
    for key, sub in origin.items():
        files = _files_in(sub)
        if isinstance(sub, dict) and len(files) > 1:
            keys += _keys_of(sub, file, f"{prefix}{key}.")
        elif file in files:
            keys.append(f"{prefix}{key}")
    return sorted(keys)
