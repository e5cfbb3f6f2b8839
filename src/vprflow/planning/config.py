"""Config validation: JSON schema (``workflow/schemas/config.schema.yaml``) plus its defaults.

The schema is the one place that states a setting's default: :func:`validate_config`
fills every ``default`` it declares, at any depth (through ``$ref`` definitions, the
entries of ``datasets``, ``backbones`` and ``segmenters``, and the ``then`` of an
``if``/``then`` the instance meets, for defaults of one ground-truth kind), then each
backbone and segmenter entry's kind defaults from :mod:`vprflow.core.registry`. Objects the
schema marks ``x-partial`` (a method's overrides, a dataset's ``defaults``) stay as
written: they are merged over the filled top-level sections
(:func:`vprflow.planning.plan.resolve_method`), and the plan fills the search index's parameter
defaults into the merged ``retrieval`` (:func:`vprflow.core.registry.search_settings`).
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

import yaml

from vprflow.core.errors import ConfigError
from vprflow.core.registry import (
    AGGREGATORS,
    BACKBONES,
    RERANKERS,
    SEARCH_INDEXES,
    SEGMENTERS,
    with_defaults,
)

# Top-level sections that every method inherits (each may be omitted: its schema default is {}).
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


# A config as written holds a few thousand values; one that expands past this many (a
# YAML alias bomb: nested aliases PyYAML builds once and shares, exponential when
# walked) is refused before validation walks it or an error message prints it.
MAX_CONFIG_VALUES = 200_000
# What an error message shows of a value at most.
MAX_SHOWN = 200


def validate_config(config: dict, schema_path: str | Path, files=()) -> dict:
    """Check ``config`` against the schema and return a copy with defaults filled in.

    Raises :class:`ConfigError` naming the offending key (e.g. an unknown key, or a key
    the entry's kind does not read: :func:`unread_keys`). ``files``: the config files
    ``config`` was read from: each is read again to refuse a key given twice
    (:func:`check_config_files`) and named when it is too large (:func:`check_config_size`).
    """
    import jsonschema

    from vprflow.data.presets import presets, protocol, with_presets

    check_config_files(files)
    check_config_size(config, files)
    schema = load_schema(schema_path)
    if isinstance(config.get("data_root"), str):
        config = {**config, "datasets": with_presets(config)}
    errors = sorted(
        jsonschema.Draft202012Validator(schema).iter_errors(config),
        key=lambda e: list(map(str, e.absolute_path)),
    )
    if errors:
        lines = []
        for error in errors[:10]:
            where = ".".join(str(p) for p in error.absolute_path) or "(top level)"
            message = error.message
            if error.validator == "pattern" and "x-error" in error.schema:  # a name's
                message = f"{shorten(error.instance)} {error.schema['x-error']}"
            lines.append(f"  config key '{where}': {shorten(message, quote=False)}")
        raise ConfigError("invalid configuration:\n" + "\n".join(lines))
    unread = unread_keys(config, schema)
    if unread:
        raise ConfigError("invalid configuration:\n" + "\n".join(f"  {u}" for u in unread[:10]))
    config = copy.deepcopy(config)
    fill_defaults(config, schema)
    for name, dataset in config["datasets"].items():
        if name in presets():
            preset = copy.deepcopy(presets()[name].dataset)
            fill_defaults(preset, schema, "#/definitions/dataset")
            # Set here, after validation: a fact about the entry, not a setting.
            dataset["protocol"] = protocol(name, preset, dataset)
    unknown = [name for name in config["targets"] if name not in config["datasets"]]
    if unknown:
        raise ConfigError(
            f"config key 'targets' names datasets {shorten(unknown)} that are not "
            f"configured; configured: {shorten(sorted(config['datasets']))}"
        )
    for entries, stage in (("backbones", "features"), ("segmenters", "segments")):
        for entry in config[entries].values():
            # Kind-specific defaults (a DINOv2 layer, SAM thresholds) from the registry.
            entry.update(with_defaults(stage, entry))
    return config


def shorten(value, quote: bool = True) -> str:
    """``value`` (its repr, or the text itself with ``quote=False``) cut to
    :data:`MAX_SHOWN` characters, for an error message."""
    text = repr(value) if quote else str(value)
    return (
        text if len(text) <= MAX_SHOWN else f"{text[: MAX_SHOWN - 30]}... ({len(text)} characters)"
    )


def count_values(value, limit: int) -> int:
    """How many values ``value`` holds, counting every container and scalar at every
    depth (a shared one once per reference, as it expands), stopping at ``limit``."""
    count, stack = 0, [value]
    while stack and count < limit:
        item = stack.pop()
        count += 1
        if isinstance(item, dict):
            stack.extend(item.keys())
            stack.extend(item.values())
        elif isinstance(item, (list, tuple)):
            stack.extend(item)
    return count


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping (PyYAML, and so
    Snakemake, keeps the last one silently)."""

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            first: dict = {}
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":  # `<<:` merges, not a key
                    continue
                key = self.construct_object(key_node, deep=deep)
                line = key_node.start_mark.line + 1
                try:
                    if key in first:
                        raise ConfigError(
                            f"config file {self.name}: key {shorten(key)} is given twice in "
                            f"one mapping, on line {first[key]} and line {line}; YAML would "
                            "keep only the second (merge the two into one)"
                        )
                    first[key] = line
                except TypeError:  # an unhashable key: the constructor names it
                    pass
        return super().construct_mapping(node, deep=deep)


def check_config_files(files=()) -> None:
    """Read each config file again, refusing a key given twice in one mapping, naming the
    file, the key and both lines: pasting a second ``datasets:`` block used to replace
    the first without a word."""
    for path in files:
        try:
            with open(path, encoding="utf-8") as stream:
                yaml.load(stream, Loader=_UniqueKeyLoader)
        except (OSError, UnicodeDecodeError, yaml.YAMLError):
            continue  # Snakemake read it; its own errors are reported elsewhere


def check_config_size(config: dict, files=()) -> None:
    """Refuse a config that expands to :data:`MAX_CONFIG_VALUES` values or more (a YAML
    alias bomb), naming which of ``files`` (the config files it was read from) does,
    in well under a second: walking it, validating it or printing it would take
    minutes and end in a MemoryError."""
    if count_values(config, MAX_CONFIG_VALUES) < MAX_CONFIG_VALUES:
        return
    culprits = []
    for path in files:
        try:
            loaded = yaml.load(Path(path).read_text(), Loader=yaml.SafeLoader)
        except (OSError, yaml.YAMLError):
            continue
        if count_values(loaded, MAX_CONFIG_VALUES) >= MAX_CONFIG_VALUES:
            culprits.append(str(path))
    where = f"config file {', '.join(culprits)}" if culprits else "the configuration"
    if not culprits and files:
        where += f" (read from {', '.join(map(str, files))} and the command line)"
    raise ConfigError(
        f"{where} expands to more than {MAX_CONFIG_VALUES:,} values (YAML aliases nested "
        "into an exponential structure?); refused before validation, which would take "
        "minutes and run out of memory"
    )


def kind_keys(definition: dict, kind_key: str) -> dict[str, list[str]]:
    """Kind -> the keys an entry of that kind reads, for a schema definition (or
    property) whose ``kind_key`` names its kind: every key but those whose ``x-kinds``
    (the kinds that read them) leaves the kind out. The kinds are ``kind_key``'s enum.
    A key's ``x-sources`` further limits it to entries whose ``source`` (when written)
    is one of them (:func:`unread_keys`)."""
    properties = definition["properties"]
    kinds = properties[kind_key]["enum"]
    return {
        kind: [name for name, prop in properties.items() if kind in prop.get("x-kinds", kinds)]
        for kind in kinds
    }


def unread_keys(config: dict, schema: dict) -> list[str]:
    """One line per key of ``config`` (as written, before defaults: a valid one) that the
    kind of its section does not read, naming the key, the kind and the kind's keys:
    a ground truth's ``kind``, a backbone's ``backbone``, a segmenter's ``segmenter``, a
    re-ranker's ``kind`` and a vocabulary's ``source`` (a method's or a dataset's
    ``vocabulary`` overrides: the source it ends up with). Such a key would be ignored
    while the table, which lists it, says it applied."""
    definitions = schema["definitions"]
    dataset = definitions["dataset"]["properties"]
    found: list[str] = []

    def check(entry: dict, definition: dict, kind_key: str, where: str, kind=None) -> None:
        kind = entry.get(kind_key, kind)
        keys = kind_keys(definition, kind_key).get(kind)
        if keys is None:
            return
        found.extend(
            f"config key '{where}.{name}': {kind_key} {kind!r} does not read {name!r}; "
            f"its keys: {', '.join(keys)}"
            for name in entry
            if name not in keys
        )
        # A key read only under some `source` of its kind (a coordinates truth's `file`).
        source = entry.get("source")
        for name in entry:
            sources = definition["properties"][name].get("x-sources")
            if name in keys and sources is not None and source not in (None, *sources):
                found.append(
                    f"config key '{where}.{name}': source {source!r} does not read {name!r}; "
                    f"it is read with source {' or '.join(map(repr, sources))}"
                )

    for name, entry in config["datasets"].items():
        check(
            entry["ground_truth"], dataset["ground_truth"], "kind", f"datasets.{name}.ground_truth"
        )
    for section, definition, kind_key in (
        ("backbones", "backbone", "backbone"),
        ("segmenters", "segmenter", "segmenter"),
        ("rerankers", "reranker", "kind"),
    ):
        for name, entry in config.get(section, {}).items():
            check(entry, definitions[definition], kind_key, f"{section}.{name}")
    vocabulary = definitions["vocabulary"]
    default = vocabulary["properties"]["source"]["default"]
    top = config.get("vocabulary", {})
    check(top, vocabulary, "source", "vocabulary", default)
    for name, entry in config["datasets"].items():
        own = entry.get("defaults", {}).get("vocabulary", {})
        if "source" in own:  # without one, its keys serve methods of any source
            check(own, vocabulary, "source", f"datasets.{name}.defaults.vocabulary")
    for name, method in config["methods"].items():
        own = method.get("vocabulary", {})
        # The source it gets from the merge, on each dataset that runs it (a method no
        # dataset runs takes effect nowhere).
        sources = {
            own.get("source")
            or entry.get("defaults", {}).get("vocabulary", {}).get("source")
            or top.get("source", default)
            for entry in config["datasets"].values()
            if name in entry["methods"]
        }
        for source in sorted(sources):
            check(own, vocabulary, "source", f"methods.{name}.vocabulary", source)
    return list(dict.fromkeys(found))


def load_schema(path: str | Path) -> dict:
    """The schema file, completed with the lists the code owns: the names of backbones,
    segmenters, aggregators and search indexes (:mod:`vprflow.core.registry`), of
    ground-truth kinds (:data:`vprflow.data.ground_truth.KINDS`) and of published vocabularies
    (:data:`vprflow.aggregation.vocabularies.PUBLISHED`) as enums, and each method
    section of :data:`METHOD_DEFAULT_SECTIONS` as a top-level key, a method key and a
    dataset ``defaults`` key (each a reference to the section's definition)."""
    from vprflow.aggregation.vocabularies import PUBLISHED as PUBLISHED_VOCABULARIES
    from vprflow.data.ground_truth import KINDS

    schema = yaml.safe_load(Path(path).read_text())
    definitions = schema["definitions"]
    for names, definition, key in (
        (BACKBONES, definitions["backbone"], "backbone"),
        (SEGMENTERS, definitions["segmenter"], "segmenter"),
        (AGGREGATORS, definitions["method"], "aggregator"),
        (SEARCH_INDEXES, definitions["retrieval"], "index"),
        (RERANKERS, definitions["reranker"], "kind"),
        (KINDS, definitions["dataset"]["properties"]["ground_truth"], "kind"),
        (PUBLISHED_VOCABULARIES, definitions["vocabulary"], "name"),
    ):
        definition["properties"][key]["enum"] = list(names)
    method = definitions["method"]["properties"]
    dataset_defaults = definitions["dataset"]["properties"]["defaults"]["properties"]
    top: dict = {}
    for name, prop in schema["properties"].items():
        if name == "methods":  # the sections read best just before the methods
            top.update(_method_section_keys(definitions))
        top[name] = prop
    schema["properties"] = top
    for section in METHOD_DEFAULT_SECTIONS:
        ref = f"#/definitions/{section}"
        method[section] = {"$ref": ref, "description": f"overrides of the `{section}` section"}
        dataset_defaults[section] = {
            "$ref": ref,
            "description": f"this dataset's `{section}` defaults",
        }
    return schema


def _method_section_keys(definitions: dict) -> dict:
    keys = {}
    for section in METHOD_DEFAULT_SECTIONS:
        if section not in definitions:
            raise ValueError(f"method section {section!r} has no schema definition")
        keys[section] = {
            "$ref": f"#/definitions/{section}",
            "default": {},
            "description": f"defaults of every method's `{section}` section (see `{section}`)",
        }
    return keys


def fill_defaults(instance: dict, schema: dict, at: str = "#") -> dict:
    """Fill into ``instance`` (in place, and return it) every default the part of
    ``schema`` at ``at`` (a local reference such as ``"#/definitions/dataset"``) declares
    for it, at any depth; see the module docstring. ``instance`` need not be valid: what
    is missing without a default stays missing."""
    import jsonschema

    validator = jsonschema.Draft202012Validator(schema)
    _fill(instance, {"$ref": at} if at != "#" else schema, validator)
    return instance


def _fill(instance, part: dict, validator) -> None:
    part = _resolve(part, validator.schema)
    if not isinstance(instance, dict) or part.get("x-partial"):
        return
    properties = part.get("properties", {})
    for name, prop in properties.items():
        if name not in instance and "default" in prop:
            instance[name] = copy.deepcopy(prop["default"])
        if name in instance:
            _fill(instance[name], prop, validator)
    entries = part.get("additionalProperties")
    if isinstance(entries, dict):
        for name, value in instance.items():
            if name not in properties:
                _fill(value, entries, validator)
    for sub in part.get("allOf", []):
        _fill(instance, sub, validator)
    if "if" in part:
        # A default of one kind (e.g. utm's radius) sits in the `then` of its `if`.
        branch = "then" if validator.evolve(schema=part["if"]).is_valid(instance) else "else"
        if branch in part:
            _fill(instance, part[branch], validator)


def _resolve(part: dict, root: dict) -> dict:
    """``part`` with its ``$ref`` (a ``#/...`` reference into ``root``) replaced by what
    it names; keywords beside the ``$ref`` (a description, a default) win."""
    while "$ref" in part:
        ref = part["$ref"]
        if not ref.startswith("#"):
            raise ValueError(f"schema reference {ref!r} is not local (#/...)")
        target = root
        for name in filter(None, ref[1:].split("/")):
            target = target[name]
        part = {**target, **{k: v for k, v in part.items() if k != "$ref"}}
    return part


# ------------------------------------------------------------------ config/README.md

_README_HEAD = """# Configuration

`config/config.yaml` is the configuration the workflow reads (pass another with
`--configfile`). It is validated against `workflow/schemas/config.schema.yaml`: an
unknown key is an error that names it, and so is a key that the entry's kind does not
read (a ground truth's `kind`, a backbone's `backbone`, a segmenter's `segmenter`, a
re-ranker's `kind`, a vocabulary's `source`): the error lists the kind's keys. Every
`default` below is filled in before anything is hashed, so a store's key and attributes
record what ran. Names of datasets, methods, backbones, segmenters and re-rankers are
plain names (letters, digits, `_`, `.`, `-`, starting with a letter or digit): they
become file and folder names under `results/` and `logs/`.

A method's settings are, later winning: the top-level sections
({sections}),
then the dataset's `defaults`, then the method's own. Backbone and segmenter entries
also get their kind's defaults, and a method's `retrieval.params` its index's, from
`src/vprflow/core/registry.py` (listed below by kind and by index). A default followed by a
condition in brackets applies only then. What the methods compute is in
`docs/methods.md`.

This file is generated from the schema's descriptions and config/config.yaml by
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
        return _REF_TEXT.get(name, f"see `{name}`")
    kind = prop.get("type", "")
    if kind == "array":
        return f"list of {_allowed(prop.get('items', {}))}"
    if kind == "object" and isinstance(prop.get("additionalProperties"), dict):
        return f"name -> {_allowed(prop['additionalProperties'])}"
    bounds = [f"{op} {prop[key]}" for key, op in _BOUNDS if key in prop]
    kind = " or ".join(kind) if isinstance(kind, list) else kind
    return ", ".join([kind, *bounds]) if kind else ""


_REF_TEXT = {"size": "[width, height]", "name": "plain name"}
_BOUNDS = (("minimum", ">="), ("exclusiveMinimum", ">"), ("maximum", "<="))


def _table(title: str, definition: dict, kinds: dict | None = None) -> list[str]:
    """A section's table; ``kinds``: the registry's kinds whose defaults its entries get."""
    required = set(definition.get("required", []))
    defaults = _conditional_defaults(definition)
    for kind in (kinds or {}).values():
        for name, value in kind.defaults.items():
            defaults.setdefault(name, {}).setdefault(json.dumps(value), []).append(kind.name)
    lines = [f"## `{title}`", ""]
    if definition.get("description"):
        lines += [definition["description"], ""]
    lines += ["| key | allowed | default | meaning |", "|---|---|---|---|"]
    for name, prop in definition.get("properties", {}).items():
        default = "required" if name in required else ""
        if "default" in prop:
            default = f"`{json.dumps(prop['default'])}`"
        elif name in defaults:
            default = ", ".join(
                f"`{value}` ({', '.join(where)})" for value, where in defaults[name].items()
            )
        meaning = prop.get("description", "").replace("|", "\\|")
        lines.append(f"| `{name}` | {_allowed(prop)} | {default} | {meaning} |")
    return [*lines, ""]


def _conditional_defaults(definition: dict) -> dict[str, dict[str, list[str]]]:
    """Key -> default -> the conditions under which it applies, from the definition's
    ``allOf`` of ``if``/``then`` (e.g. ``kind utm``)."""
    found: dict[str, dict[str, list[str]]] = {}
    for part in definition.get("allOf", []):
        condition = part.get("if", {}).get("properties", {})
        when = " and ".join(f"{k} {v['const']}" for k, v in condition.items() if "const" in v)
        for name, prop in part.get("then", {}).get("properties", {}).items():
            if "default" in prop:
                found.setdefault(name, {}).setdefault(json.dumps(prop["default"]), []).append(when)
    return found


def _search_index_table() -> list[str]:
    lines = [
        "## `retrieval.params` by index",
        "",
        "Each index's parameters and their defaults (`src/vprflow/core/registry.py`), filled into "
        "a method's `retrieval.params` before hashing; `null` = chosen by `vprflow.search` "
        "(`nlist`, `m`: from the data; `margin`: by `candidate_dtype`). An approximate "
        "index's table also reports an exact search's recall.",
        "",
        "| index | exact | parameters (default) |",
        "|---|---|---|",
    ]
    for index in SEARCH_INDEXES.values():
        params = ", ".join(f"`{k}` (`{json.dumps(v)}`)" for k, v in index.defaults.items())
        exact = "yes" if index.exact else "no"
        lines.append(f"| `{index.name}` | {exact} | {params or 'none'} |")
    return [*lines, ""]


def config_readme(schema: dict, shipped: dict | None = None) -> str:
    """``config/README.md``: what the shipped config (``shipped``, config/config.yaml as
    read) defines, then every key of the schema, its allowed values, default (the
    schema's, its kind's from the registry) and meaning (the schema's ``description``s),
    and each search index's parameter defaults."""
    sections = ", ".join(f"`{name}`" for name in METHOD_DEFAULT_SECTIONS)
    lines = [_README_HEAD.replace("{sections}", sections)]
    if shipped is not None:
        lines += _shipped_tables(shipped)
    lines += _table("top level", schema)
    kinds = {"backbone": BACKBONES, "segmenter": SEGMENTERS}
    for name, definition in schema["definitions"].items():
        if "properties" not in definition:
            continue
        lines += _table(name, definition, kinds.get(name))
        for sub, prop in definition["properties"].items():
            if "properties" in prop:
                lines += _table(f"{name}.{sub}", prop)
        if name == "retrieval":
            lines += _search_index_table()
    return "\n".join(lines).rstrip() + "\n"


# What a shipped entry is, in a table cell: the keys that tell entries apart.
_SHIPPED_KEYS = {
    "backbones": ("backbone", "model", "layer", "facet", "file"),
    "segmenters": ("segmenter", "model", "n_segments", "file"),
    "rerankers": ("kind", "features"),
}


def _flow(value) -> str:
    """``value`` as one line of YAML, as a config would write it."""
    return yaml.safe_dump(value, default_flow_style=True, width=10**6).strip()


def _shipped_tables(shipped: dict) -> list[str]:
    """The entries config/config.yaml defines (backbones, segmenters, re-rankers,
    methods, datasets) and its ``data_root``, one table row each."""

    def cell(entry: dict, keys) -> str:
        return ", ".join(f"{k}: `{entry[k]}`" for k in keys if entry.get(k) is not None)

    lines = [
        "## What `config/config.yaml` ships",
        "",
        f"`data_root` is `{shipped['data_root']}` (relative to the directory Snakemake runs "
        "in; `--config data_root=...` points elsewhere). `device` is "
        f"`{shipped.get('device', 'auto')}`; `targets`: "
        f"{', '.join(f'`{t}`' for t in shipped.get('targets', [])) or 'none'}.",
        "",
    ]
    for section, keys in _SHIPPED_KEYS.items():
        lines += [f"`{section}`:", "", "| name | what |", "|---|---|"]
        lines += [f"| `{n}` | {cell(e, keys)} |" for n, e in shipped.get(section, {}).items()]
        lines.append("")
    lines += ["`methods` (an aggregator, and what the method overrides):", ""]
    lines += ["| name | aggregator | overrides |", "|---|---|---|"]
    for name, method in shipped["methods"].items():
        overrides = {k: v for k, v in method.items() if k != "aggregator"}
        text = ", ".join(f"`{_flow({k: v})}`" for k, v in overrides.items()) or "-"
        lines.append(f"| `{name}` | `{method['aggregator']}` | {text} |")
    lines += ["", "`datasets` (the papers' datasets are presets: docs/datasets.md):", ""]
    lines += ["| name | methods | re-ranked |", "|---|---|---|"]
    for name, dataset in shipped.get("datasets", {}).items():
        methods = ", ".join(f"`{m}`" for m in dataset.get("methods", []))
        rerank = "; ".join(
            f"`{m}` by {', '.join(f'`{r}`' for r in rs)}"
            for m, rs in (dataset.get("rerank") or {}).items()
        )
        lines.append(f"| `{name}` | {methods} | {rerank or '-'} |")
    return [*lines, ""]
