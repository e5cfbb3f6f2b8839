"""Where model weights come from: a local directory or a Hugging Face hub id.

A config's ``model`` value is either

- a local directory holding a transformers ``config.json`` and weights
  (``*.safetensors`` or ``*.bin``), used as is; or
- a hub id such as ``facebook/dinov2-giant``, looked up in (and, with a network,
  downloaded into) the Hugging Face cache under ``cache_dir`` (the default HF cache
  when ``None``). ``HF_HUB_OFFLINE=1`` is honoured even when it is set after
  ``huggingface_hub`` was imported.

When neither works, :class:`ModelNotFoundError` names the model and both remedies.
"""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

from vprflow.core.lazy import lazy_import

# planning/fingerprints.py and stages/base.py read this module: huggingface_hub's
# download code (~0.1 s to import) only when a model is looked up.
huggingface_hub = lazy_import("huggingface_hub")
hub_constants = lazy_import("huggingface_hub.constants")

WEIGHT_PATTERNS = ("*.safetensors", "*.bin")
# Hub ids are "name" or "owner/name" of letters, digits, "-", "_", "."; anything else
# (absolute paths, "./x", "~/x", "a/b/c") can only be a local path.
_HUB_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*(/[A-Za-z0-9][A-Za-z0-9._-]*)?$")
_TRUE = {"1", "on", "yes", "true"}


class ModelNotFoundError(FileNotFoundError):
    """A model that is neither a usable local directory nor obtainable from the hub."""


def model_not_found(model: str, reason: str, cache_dir: str | None) -> ModelNotFoundError:
    hub_id = model if _HUB_ID.match(model) else "<hub-id>"
    cache = f"cache_dir {cache_dir!r}" if cache_dir else "the default Hugging Face cache"
    return ModelNotFoundError(
        f"model {model!r} is not available: {reason}\n"
        "Supply it in one of two ways:\n"
        f"  1. from the Hugging Face hub: with network access, set `model` to the hub id and "
        f"it is downloaded into {cache} (HF_HUB_OFFLINE must be unset for that run); or, on "
        f"a machine with network, run `huggingface-cli download {hub_id} --local-dir DIR` "
        f"(newer huggingface_hub: `hf download {hub_id} --local-dir DIR`) and copy DIR here;\n"
        "  2. set the config key `model` to a local directory DIR holding config.json and "
        "*.safetensors or *.bin weight files (e.g. the DIR of step 1)."
    )


def _offline() -> bool:
    # huggingface_hub reads HF_HUB_OFFLINE once at import; re-read the environment so a
    # value set later (tests, wrappers) still counts.
    env = (os.environ.get(name, "") for name in ("HF_HUB_OFFLINE", "TRANSFORMERS_OFFLINE"))
    return bool(hub_constants.HF_HUB_OFFLINE) or any(v.strip().lower() in _TRUE for v in env)


def _weight_files(directory: Path) -> list[Path]:
    files = {p for pattern in WEIGHT_PATTERNS for p in directory.glob(pattern) if p.is_file()}
    return sorted(files)


def is_local_model(model: str) -> bool:
    """True when ``model`` names a local path (existing, or not shaped like a hub id)."""
    path = Path(model).expanduser()
    return path.exists() or not _HUB_ID.match(model)


def _check_local(model: str, cache_dir: str | None) -> str:
    path = Path(model).expanduser()
    if not path.exists():
        raise model_not_found(model, f"local directory {str(path)!r} does not exist", cache_dir)
    if not path.is_dir():
        raise model_not_found(model, f"{str(path)!r} is not a directory", cache_dir)
    if not (path / "config.json").is_file():
        raise model_not_found(model, f"directory {str(path)!r} has no config.json", cache_dir)
    if not _weight_files(path):
        raise model_not_found(
            model, f"directory {str(path)!r} has no *.safetensors or *.bin weights", cache_dir
        )
    return str(path.resolve())


def _download(model: str, cache_dir: str | None, offline: bool, weights: str) -> Path:
    # Only config/preprocessor JSON and one weight format: hub repos often also carry
    # TensorFlow / Flax copies that would multiply the download.
    return Path(
        huggingface_hub.snapshot_download(
            repo_id=model,
            cache_dir=cache_dir,
            local_files_only=offline,
            allow_patterns=["*.json", weights],
        )
    )


def resolve_model_source(model: str, cache_dir: str | None = None) -> str:
    """Return a local directory with ``config.json`` + weights for ``model``.

    ``model`` is a local directory or a hub id (see the module docstring). For a hub id
    the result is the snapshot directory inside the HF cache; safetensors weights are
    preferred, ``*.bin`` fetched only when the repository has no safetensors. Raises
    :class:`ModelNotFoundError` when the model cannot be found or downloaded.
    """
    model = str(model).strip()
    if not model:
        raise model_not_found(model, "empty model name", cache_dir)
    if is_local_model(model):
        return _check_local(model, cache_dir)

    offline = _offline()
    try:
        snapshot = _download(model, cache_dir, offline, "*.safetensors")
        if not _weight_files(snapshot) and not offline:
            snapshot = _download(model, cache_dir, offline, "*.bin")
    except (OSError, ValueError) as error:
        # OSError covers every hub failure (not found, gated, offline, no connection);
        # ValueError covers malformed ids.
        if offline:  # the hub's own message suggests flags that are ours to set
            reason = "hub id not in the cache, and HF_HUB_OFFLINE is set"
        else:
            lines = str(error).strip().splitlines() or [""]
            reason = f"hub download failed ({type(error).__name__}: {lines[0]})"
        raise model_not_found(model, reason, cache_dir) from error
    if not (snapshot / "config.json").is_file() or not _weight_files(snapshot):
        raise model_not_found(
            model, f"the cached snapshot {str(snapshot)!r} lacks config.json or weights", cache_dir
        )
    return str(snapshot)


class ModelLoadError(ValueError):
    """Model files that exist but cannot be loaded; the message names the directory."""


def load_pretrained(load, source: str, model: str, **kwargs):
    """``load(source, **kwargs)`` (a transformers ``from_pretrained``), with any failure
    (corrupt or truncated safetensors, a refused ``*.bin`` pickle, a wrong architecture)
    turned into a :class:`ModelLoadError` that names the directory and the remedy."""
    try:
        return load(source, **kwargs)
    except Exception as error:  # loaders raise many unrelated types for a bad file
        first = (str(error).strip().splitlines() or [""])[0][:300]
        raise ModelLoadError(
            f"model {model!r}: cannot load the files in {source} ({type(error).__name__}: "
            f"{first}). They are corrupt, truncated, of another architecture, or *.bin "
            "pickles that are refused (only plain tensors are read). Download the model "
            "again (`huggingface-cli download <hub-id> --local-dir DIR`, safetensors "
            "preferred) or set the config key `model` to an intact directory."
        ) from error


def _hash_file(digest, path: Path, chunk: int = 1 << 22) -> None:
    with path.open("rb") as handle:
        while block := handle.read(chunk):
            digest.update(block)


def weights_fingerprint(path_or_id: str) -> str:
    """A short string that changes when the model's weights change.

    Local directory: ``"sha256:<hex>"`` over ``config.json`` and every ``*.safetensors``
    / ``*.bin`` file (names, sizes and bytes, in sorted order), read in 4 MiB chunks.
    Hub id: ``"hf:<id>"``. The id alone is used (not the cached revision) so the key is
    the same before and after the first download; pin a revision by downloading it to a
    local directory.
    """
    text = str(path_or_id).strip()
    if not is_local_model(text):
        return f"hf:{text}"
    directory = Path(_check_local(text, None))
    digest = hashlib.sha256()
    files = _weight_files(directory) + [directory / "config.json"]
    for path in sorted(files):
        # Names and sizes go in too, so renaming or splitting shards changes the key.
        digest.update(f"{path.name}\0{path.stat().st_size}\0".encode())
        _hash_file(digest, path)
    return f"sha256:{digest.hexdigest()}"
