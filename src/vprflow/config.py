"""Config validation: JSON schema (``workflow/schemas/config.schema.yaml``) plus its defaults.

The schema is the one place that states a setting's default: :func:`validate_config`
fills every ``default`` it declares for top-level settings, the method sections
(``vocabulary``, ``vlad``, ``pca``, ``segvlad``, ``snsm``, ``pooling``), each
dataset and each backbone and segmenter entry. Method overrides and a dataset's
``defaults`` stay partial on purpose: they are merged over the filled top-level
sections (see :func:`vprflow.plan.resolve_method`).
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

import yaml

from vprflow.registry import (
    AGGREGATORS,
    BACKBONES,
    KIND_KEY,
    SEARCH_INDEXES,
    SEGMENTERS,
    with_defaults,
)

# Top-level sections that every method inherits and that may be omitted entirely.
METHOD_DEFAULT_SECTIONS = (
    "vocabulary",
    "vlad",
    "pca",
    "segvlad",
    "voting",
    "retrieval",
    "snsm",
    "pooling",
)


class ConfigError(ValueError):
    """Invalid configuration; the message names the key at fault."""


def validate_config(config: dict, schema_path: str | Path) -> dict:
    """Check ``config`` against the schema and return a copy with defaults filled in.

    Raises :class:`ConfigError` naming the offending key (e.g. an unknown key).
    """
    import jsonschema

    schema = yaml.safe_load(Path(schema_path).read_text())
    _set_registry_enums(schema)
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
    config["figures"] = config.get("figures") or {}
    _fill_defaults(config["figures"], schema["definitions"]["figures"])
    for dataset in config["datasets"].values():
        _fill_defaults(dataset, schema["definitions"]["dataset"])
    unknown = [name for name in config["targets"] if name not in config["datasets"]]
    if unknown:
        raise ConfigError(
            f"config key 'targets' names datasets {unknown} that are not configured; "
            f"configured: {sorted(config['datasets'])}"
        )
    for entries, stage in (("backbones", "features"), ("segmenters", "segments")):
        for entry in config[entries].values():
            _fill_defaults(entry, schema["definitions"][KIND_KEY[stage]])
            # Kind-specific defaults (a DINOv2 layer, SAM thresholds) from the registry.
            entry.update(with_defaults(stage, entry))
    return config


def registry_enums(schema: dict) -> dict[str, list[str]]:
    """The schema's lists of backbone, segmenter, aggregator and search index names (which
    ``tests/test_registry.py`` checks against :mod:`vprflow.registry`)."""
    definitions = schema["definitions"]
    return {
        "backbones": definitions["backbone"]["properties"]["backbone"]["enum"],
        "segmenters": definitions["segmenter"]["properties"]["segmenter"]["enum"],
        "aggregators": definitions["method"]["properties"]["aggregator"]["enum"],
        "search_indexes": definitions["retrieval"]["properties"]["index"]["enum"],
    }


def _set_registry_enums(schema: dict) -> None:
    """Make the registry the authority on component names, whatever the file lists."""
    enums = registry_enums(schema)
    enums["backbones"][:] = list(BACKBONES)
    enums["segmenters"][:] = list(SEGMENTERS)
    enums["aggregators"][:] = list(AGGREGATORS)
    enums["search_indexes"][:] = list(SEARCH_INDEXES)


def _fill_defaults(instance: dict, schema: dict) -> None:
    """Set every property of ``schema`` that declares a ``default`` and is missing."""
    for name, prop in schema.get("properties", {}).items():
        if "default" in prop and name not in instance:
            instance[name] = copy.deepcopy(prop["default"])


def load_config(path: str | Path, schema_path: str | Path) -> dict:
    with open(path) as f:
        return validate_config(yaml.safe_load(f), schema_path)


# ------------------------------------------------------------------ config/README.md

_README_HEAD = """# Configuration

`config/config.yaml` is the configuration the workflow reads (pass another with
`--configfile`). It is validated against `workflow/schemas/config.schema.yaml`: an
unknown key is an error that names it, and every `default` below is filled in before
anything is hashed, so a store's key and attributes record what ran.

A method's settings are, later winning: the top-level sections (`vocabulary`, `vlad`,
`pca`, `segvlad`, `retrieval`, `snsm`, `pooling`), then the dataset's `defaults`, then the method's
own. Backbone and segmenter entries also get their kind's defaults from
`src/vprflow/registry.py` (named in the descriptions below). What the methods compute
is in `docs/methods.md`.

This file is generated from the schema's descriptions by
`python scripts/write_config_readme.py`; `tests/test_registry.py` checks it is current.
"""


def _allowed(prop: dict) -> str:
    if "enum" in prop:
        return " / ".join(f"`{v}`" for v in prop["enum"])
    if "const" in prop:
        return f"`{prop['const']}`"
    if "oneOf" in prop:
        return " or ".join(_allowed(p) for p in prop["oneOf"])
    if "$ref" in prop:
        name = prop["$ref"].rsplit("/", 1)[-1]
        return "[width, height]" if name == "size" else f"see `{name}`"
    kind = prop.get("type", "")
    if kind == "array":
        return f"list of {_allowed(prop.get('items', {}))}"
    if kind == "object" and isinstance(prop.get("additionalProperties"), dict):
        return f"name -> {_allowed(prop['additionalProperties'])}"
    bounds = [f"{op} {prop[key]}" for key, op in _BOUNDS if key in prop]
    kind = " or ".join(kind) if isinstance(kind, list) else kind
    return ", ".join([kind, *bounds]) if kind else ""


_BOUNDS = (("minimum", ">="), ("exclusiveMinimum", ">"), ("maximum", "<="))


def _table(title: str, definition: dict) -> list[str]:
    required = set(definition.get("required", []))
    lines = [f"## `{title}`", ""]
    if definition.get("description"):
        lines += [definition["description"], ""]
    lines += ["| key | allowed | default | meaning |", "|---|---|---|---|"]
    for name, prop in definition.get("properties", {}).items():
        default = "required" if name in required else ""
        if "default" in prop:
            default = f"`{json.dumps(prop['default'])}`"
        meaning = prop.get("description", "").replace("|", "\\|")
        lines.append(f"| `{name}` | {_allowed(prop)} | {default} | {meaning} |")
    return [*lines, ""]


def config_readme(schema: dict) -> str:
    """``config/README.md``: every key of the schema, its allowed values, default and
    meaning (from the schema's ``description``s)."""
    lines = [_README_HEAD, *_table("top level", schema)]
    for name, definition in schema["definitions"].items():
        if "properties" not in definition:
            continue
        lines += _table(name, definition)
        for sub, prop in definition["properties"].items():
            if "properties" in prop:
                lines += _table(f"{name}.{sub}", prop)
    return "\n".join(lines).rstrip() + "\n"
