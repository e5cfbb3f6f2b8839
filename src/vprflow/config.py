"""Config validation: JSON schema (``config/schema.yaml``) plus defaults."""

from __future__ import annotations

import copy
from pathlib import Path

import yaml


class ConfigError(ValueError):
    """Invalid configuration; the message names the key at fault."""


DATASET_DEFAULTS = {"paired": False, "recall_at": [1, 5, 10, 20]}
TOP_LEVEL_DEFAULTS = {"device": "auto", "shard_size": 0}


def validate_config(config: dict, schema_path: str | Path) -> dict:
    """Check ``config`` against the schema and return a copy with defaults filled in.

    Raises :class:`ConfigError` naming the offending key (e.g. an unknown key).
    """
    import jsonschema

    schema = yaml.safe_load(Path(schema_path).read_text())
    errors = sorted(
        jsonschema.Draft202012Validator(schema).iter_errors(config),
        key=lambda e: list(map(str, e.absolute_path)),
    )
    if errors:
        lines = []
        for error in errors[:10]:
            where = ".".join(str(p) for p in error.absolute_path) or "(top level)"
            lines.append(f"  config key '{where}': {error.message}")
        raise ConfigError("invalid configuration:\n" + "\n".join(lines))
    config = copy.deepcopy(config)
    for name, value in TOP_LEVEL_DEFAULTS.items():
        config.setdefault(name, value)
    for dataset in config["datasets"].values():
        for name, value in DATASET_DEFAULTS.items():
            dataset.setdefault(name, copy.deepcopy(value))
    return config


def load_config(path: str | Path, schema_path: str | Path) -> dict:
    with open(path) as f:
        return validate_config(yaml.safe_load(f), schema_path)
