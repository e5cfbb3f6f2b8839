"""Content hashes of the files a key covers, memoised by stamp between runs.

A stage's key covers what its inputs hold, not where they are: a dataset's images and
ground truth, local model weights, imported files. The plan is built on every run, so
each file's SHA-256 is memoised by absolute path, size, mtime and ctime (one ``stat``
per file: re-planning 100,000 images, or a ViT-G checkpoint that takes seconds to hash,
is quick). The memo lives at :data:`vprflow.core.paths.FINGERPRINTS`.
"""

from __future__ import annotations

import hashlib
import json
import os
import stat
import warnings
from pathlib import Path, PurePath

from vprflow.core.errors import DatasetError, PlanError
from vprflow.core.files import link_loop, write_text_atomic
from vprflow.core.paths import FINGERPRINTS, dataset_folder
from vprflow.data.datasets import DatasetFiles, list_dataset
from vprflow.data.ground_truth import ground_truth_files
from vprflow.data.images import ImageReadError
from vprflow.models.hub import is_local_model, model_not_found, weights_fingerprint
from vprflow.models.kinds import model_kind


def file_digest(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def load_fingerprints(path: str | Path = FINGERPRINTS) -> dict:
    """The memo of content hashes (see :func:`memoised`). It is only a cache: an
    unreadable one is reported, ignored and rebuilt (hashing everything once more)."""
    path = Path(path)
    if not path.exists():
        return {}
    try:
        memo = json.loads(path.read_text())
        if not isinstance(memo, dict) or not all(isinstance(v, str) for v in memo.values()):
            raise ValueError("not a JSON object of strings")
        return memo
    except (OSError, ValueError) as error:
        warnings.warn(
            f"{path} is unreadable ({error}); it only caches content hashes, so it is "
            "ignored and rebuilt (delete it to silence this)",
            stacklevel=2,
        )
        return {}


def save_fingerprints(memo: dict, path: str | Path = FINGERPRINTS) -> None:
    """Write the memo atomically, so a concurrent or killed run never leaves half a file."""
    write_text_atomic(path, json.dumps(memo, indent=1, sort_keys=True))


def memo_key(path: str | Path, st: os.stat_result | None = None) -> str:
    """The memo's key of a file: its absolute path, size, mtime and ctime."""
    st = st or os.stat(path)
    stamp = f"{os.path.basename(path)}:{st.st_size}:{st.st_mtime_ns}:{st.st_ctime_ns}"
    return f"{os.path.abspath(path)}|{stamp}"


def memoised(path: str | Path, memo: dict, digest, where: str, folder: bool = False) -> str:
    """``digest(path)`` of a file or (``folder``: a digest that reads one) a directory's
    files, memoised by absolute path, size, mtime and ctime (one ``stat`` per file:
    re-planning 100,000 images is quick). ``where`` is the config key naming ``path``,
    named when it does not exist or is a folder where a file is read."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise PlanError(f"config key {where}: {path} does not exist") from None
    except OSError:
        _refuse_a_loop(path, where)
        raise
    if stat.S_ISDIR(st.st_mode) and not folder:
        raise PlanError(
            f"config key {where}: {path} is a folder; it must name a file{_holding(path)}"
        )
    if stat.S_ISDIR(st.st_mode):
        entries = sorted(os.scandir(path), key=lambda e: e.name)
        for entry in entries:
            if entry.is_symlink():
                _refuse_a_loop(entry.path, where)
        stamps = [(e.name, e.stat()) for e in entries if e.is_file()]
        stamp = "|".join(f"{n}:{s.st_size}:{s.st_mtime_ns}:{s.st_ctime_ns}" for n, s in stamps)
        key = f"{os.path.abspath(path)}|{stamp}"
    else:
        key = memo_key(path, st)
    if key not in memo:
        memo[key] = digest(str(path))
    return memo[key]


def _refuse_a_loop(path: str | Path, where: str) -> None:
    """A :class:`PlanError` naming ``path`` and ``where`` if ``path`` is a link in a loop
    (``os.stat`` would raise ``ELOOP``, naming no config key)."""
    loop = link_loop(path)
    if loop is not None:
        raise PlanError(
            f"config key {where}: {path} is a link in a loop ({loop}), which leads to no "
            "file: remove the links, or point one at the file"
        )


def _holding(path: str | Path, shown: int = 5) -> str:
    """What a folder named where a file was meant holds, to point at the file."""
    try:
        names = sorted(e.name for e in os.scandir(path) if not e.name.startswith("."))
    except OSError:
        return ""
    if not names:
        return " (the folder is empty)"
    more = f", ... ({len(names)} entries)" if len(names) > shown else ""
    return f" (the folder holds {', '.join(names[:shown])}{more})"


def dataset_contents(
    data_root: str, name: str, dataset: dict, memo: dict
) -> tuple[str | None, str, DatasetFiles | None]:
    """What a dataset's two stores cover of files: the images' digest
    (:func:`images_digest`, ``None`` while the dataset cannot be
    listed: its stage then fails, naming why), the ground-truth files' digest
    (:func:`truth_digest`) and the listing (or ``None``).

    Each file's hash is memoised by path, size, mtime and ctime, so re-planning reads no
    image twice; ctime changes whenever a file is rewritten, even by ``cp -p``,
    ``rsync -a`` or ``tar`` (which restore an older mtime).
    """

    def file_hash(path, where):
        return memoised(path, memo, file_digest, f"datasets.{name}.{where}")

    truth = truth_digest(data_root, dataset, file_hash)
    try:
        files = list_dataset(data_root, name, dataset)
    except (DatasetError, ImageReadError):
        return None, truth, None
    return images_digest(files, data_root, dataset, file_hash), truth, files


def images_digest(files: DatasetFiles, data_root: str | Path, dataset: dict, file_hash) -> str:
    """SHA-256 over every image's name (relative to its role's folder) and content hash,
    in order: what the images stage's key covers. ``file_hash(path, where) -> hex
    sha256``, ``where`` a config key (``reference``, ``query``) to name in errors."""

    digest = hashlib.sha256()
    root = dataset_folder(data_root, dataset)
    for role, paths in (("reference", files.reference), ("query", files.query)):
        # Named relative to the role's folder (a list file's: the dataset folder), so a
        # flat folder hashes its file names and a nested one its relative paths.
        base = root / dataset[role] if (root / dataset[role]).is_dir() else root
        start = len(str(base)) + 1  # paths are base/<relative>: cut, not relative_to
        for path in paths:
            label = PurePath(str(path)[start:]).as_posix()
            digest.update(f"{role}/{label}:{file_hash(path, role)}\n".encode())
    return digest.hexdigest()[:32]


def truth_digest(data_root: str | Path, dataset: dict, file_hash) -> str:
    """SHA-256 over the ground-truth files' names and content hashes: what the truth
    (``dataset``) stage's key covers besides the images key. ``file_hash`` as in
    :func:`images_digest` (``where`` is ``ground_truth.file``)."""

    digest = hashlib.sha256()
    for path in ground_truth_files(data_root, dataset):
        # A folder (Baidu Mall's pose files) counts by each file in it.
        members = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
        for member in members:
            if member.exists():
                sha = file_hash(member, "ground_truth.file")
                label = member.relative_to(path.parent).as_posix()
                digest.update(f"truth/{label}:{sha}\n".encode())
    return digest.hexdigest()[:32]


def source_fingerprint(stage: str, entry: dict, memo: dict, where: str = "") -> dict:
    """What identifies the weights or file a backbone (``stage="features"``) or
    segmenter (``stage="segments"``) entry reads, as its kind says (models/kinds.py).

    Hub ids stand for themselves; local model directories and imported HDF5 files are
    hashed by content (memoised by path, size and modification time, because a
    ViT-G checkpoint takes seconds to hash and the plan is built on every run), as are
    the kind's ``model_files`` in a local directory and a backbone's ``checkpoint`` file.
    ``where`` is the entry's config key (``backbones.<name>``), named in errors.
    """
    kind = model_kind(stage, entry)
    if kind.weights == "file":
        return {"file_sha256": memoised(entry["file"], memo, file_digest, f"{where}.file")}
    if kind.weights == "model":
        model = entry["model"]
        if not is_local_model(model):
            return {
                "model": model,
                "weights": f"hf:{model}",
                **_checkpoint_fingerprint(entry, memo, where),
            }
        if not Path(model).expanduser().exists():
            raise PlanError(
                f"config key {where}.model: "
                + str(model_not_found(model, f"local directory {model!r} does not exist", None))
            )
        weights = memoised(model, memo, weights_fingerprint, f"{where}.model", folder=True)
        found = {"model": model, "weights": weights}
        for name in kind.model_files:  # e.g. a DINOv3 directory's preprocessor_config.json
            path = Path(model).expanduser() / name
            if path.is_file():
                found[name] = memoised(path, memo, file_digest, f"{where}.model")
        return {**found, **_checkpoint_fingerprint(entry, memo, where)}
    return {}


def _checkpoint_fingerprint(entry: dict, memo: dict, where: str) -> dict:
    """A backbone's ``checkpoint`` file (weights replacing the model's), hashed."""
    if entry.get("checkpoint") is None:
        return {}
    sha = memoised(entry["checkpoint"], memo, file_digest, f"{where}.checkpoint")
    return {"checkpoint_sha256": sha}
