"""Config validation: JSON schema (``config/schema.yaml``) plus its defaults.

The schema is the one place that states a setting's default: :func:`validate_config`
fills every ``default`` it declares for top-level settings, the method sections
(``vocabulary``, ``vlad``, ``pca``, ``segvlad``, ``snsm``, ``pooling``), each
dataset and each backbone and segmenter entry. Method overrides and a dataset's
``defaults`` stay partial on purpose: they are merged over the filled top-level
sections (see :func:`vprflow.plan.resolve_method`).
"""

from __future__ import annotations

import copy
from pathlib import Path

import yaml

# Top-level sections that every method inherits and that may be omitted entirely.
METHOD_DEFAULT_SECTIONS = ("vocabulary", "vlad", "pca", "segvlad", "snsm", "pooling")


class ConfigError(ValueError):
    """Invalid configuration; the message names the key at fault."""


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
    _fill_defaults(config, schema)
    for section in METHOD_DEFAULT_SECTIONS:
        config[section] = config.get(section) or {}
        _fill_defaults(config[section], schema["definitions"][section])
    for dataset in config["datasets"].values():
        _fill_defaults(dataset, schema["definitions"]["dataset"])
    for entries, definition in (("backbones", "backbone"), ("segmenters", "segmenter")):
        for entry in config[entries].values():
            _fill_defaults(entry, schema["definitions"][definition])
    return config


def _fill_defaults(instance: dict, schema: dict) -> None:
    """Set every property of ``schema`` that declares a ``default`` and is missing."""
    for name, prop in schema.get("properties", {}).items():
        if "default" in prop and name not in instance:
            instance[name] = copy.deepcopy(prop["default"])


def load_config(path: str | Path, schema_path: str | Path) -> dict:
    with open(path) as f:
        return validate_config(yaml.safe_load(f), schema_path)
