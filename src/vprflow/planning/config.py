"""Config validation: JSON schema (``workflow/schemas/config.schema.yaml``) plus its defaults.

The schema is the one place that states a setting's default: :func:`validate_config`
fills every ``default`` it declares, at any depth (through ``$ref`` definitions, the
entries of ``datasets``, ``backbones`` and ``segmenters``, and the ``then`` of an
``if``/``then`` the instance meets, for defaults of one ground-truth kind), after each
backbone and segmenter entry's kind defaults from :mod:`vprflow.models.kinds` (so a
kind's default of a key every kind reads wins over the schema's). Objects the
schema marks ``x-partial`` (a method's overrides, a dataset's ``defaults``) stay as
written: they are merged over the filled top-level sections
(:func:`vprflow.planning.plan.resolve_method`), and the plan fills the search index's parameter
defaults into the merged ``retrieval`` (:func:`vprflow.search.indexes.search_settings`).
"""

from __future__ import annotations

import copy
import importlib
import math
from pathlib import Path

import yaml

from vprflow.aggregation.aggregators import AGGREGATORS
from vprflow.aggregation.vocabularies import PUBLISHED as PUBLISHED_VOCABULARIES
from vprflow.core.errors import ConfigError, short_repr
from vprflow.core.lazy import lazy_import
from vprflow.data.ground_truth import KINDS
from vprflow.data.presets import Components, presets, protocol, with_presets
from vprflow.evaluation.rerank import RERANKERS
from vprflow.models.kinds import BACKBONES, SEGMENTERS, TRAINED_KINDS, with_defaults
from vprflow.planning.merges import dataset_merges, say_merges, without_foreign_downloads
from vprflow.search.indexes import SEARCH_INDEXES

# Read when a config is validated (~40 ms to import), not by every reader of its constants.
jsonschema = lazy_import("jsonschema")

# The modules whose constants a schema `x-enum` may name: the config is validated
# without importing torch, so each of these must import without it (test_enumerations).
ENUM_MODULES = (
    "vprflow.core.dtypes",
    "vprflow.core.masks",
    "vprflow.data.images",
    "vprflow.models.kinds",
    "vprflow.aggregation.aggregators",
    "vprflow.search.voting",
    "vprflow.aggregation.vlad",
    "vprflow.aggregation.pca",
    "vprflow.aggregation.segvlad",
    "vprflow.aggregation.snsm",
    "vprflow.evaluation.recall",
    "vprflow.evaluation.rerank",
)

# The sections of the stages that several aggregators share; an aggregator's own
# settings are its entry's `sections` (aggregation/aggregators.py).
SHARED_SECTIONS = ("vocabulary", "pca", "voting", "retrieval")
# The order of the method sections: it reaches the resolved settings and the tables'
# columns, so it is fixed here rather than left to AGGREGATORS' order; a section not in
# it (a new aggregator's) follows them in AGGREGATORS order.
SECTION_ORDER = ("vocabulary", "vlad", "pca", "segvlad", "voting", "retrieval", "snsm", "pooling")


def method_default_sections() -> tuple[str, ...]:
    """The shared sections and every aggregator's ``sections``, once each, in
    :data:`SECTION_ORDER` then :data:`AGGREGATORS` order."""
    named = dict.fromkeys(
        [*SHARED_SECTIONS, *(s for agg in AGGREGATORS.values() for s in agg.sections)]
    )
    return (
        *(s for s in SECTION_ORDER if s in named),
        *(s for s in named if s not in SECTION_ORDER),
    )


# Top-level sections that every method inherits (each may be omitted: its schema default is {}).
METHOD_DEFAULT_SECTIONS = method_default_sections()


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
    Given in merge order, they also say which keys of a dataset that two files define
    came from which (:mod:`vprflow.planning.merges`, which also drops a ``download`` that
    would lay out another file's folder).
    A NaN or infinite number is refused wherever it is (:func:`non_finite_numbers`), and
    an integral float where the schema expects an integer is read as that integer
    (:func:`integral_floats`), so ``n_clusters: 8.0`` runs, and is keyed, as ``8``.
    """
    check_config_files(files)
    merges = dataset_merges(files)
    say_merges(merges)
    config = without_foreign_downloads(config, merges)
    check_config_size(config, files)
    schema = load_schema(schema_path)
    if isinstance(config.get("data_root"), str):
        components = Components(
            vocabulary_aggregators={n for n, a in AGGREGATORS.items() if "vocabulary" in a.needs},
            trained_kinds=TRAINED_KINDS,
            fill_backbone=lambda entry: with_defaults("features", entry),
        )
        config = {**config, "datasets": with_presets(config, components)}
    # A copy: integral floats are made integers in it, and defaults filled.
    config = copy.deepcopy(config)
    non_finite = non_finite_numbers(config)
    lines = [
        f"  config key '{_dotted(path)}': {value} is not a finite number; every number "
        "in the configuration (a distance, radius, threshold, size or count) must be finite"
        for path, value in non_finite
    ]
    refused = {_dotted(path) for path, _ in non_finite}
    for path in integral_floats(config, schema):
        _set(config, path, int(_get(config, path)))
    errors = sorted(
        (
            error
            for error in jsonschema.Draft202012Validator(schema).iter_errors(config)
            if _dotted(error.absolute_path) not in refused
        ),
        key=lambda e: list(map(str, e.absolute_path)),
    )
    for error in errors[:10]:
        message = error.message
        if error.validator == "pattern" and "x-error" in error.schema:  # a name's
            message = f"{short_repr(error.instance, MAX_SHOWN)} {error.schema['x-error']}"
        lines.append(
            f"  config key '{_dotted(error.absolute_path)}': "
            f"{short_repr(message, MAX_SHOWN, quote=False)}{string_hint(error, schema)}"
        )
    if lines:
        raise ConfigError("invalid configuration:\n" + "\n".join(lines[:10]))
    unread = unread_keys(config, schema)
    if unread:
        raise ConfigError("invalid configuration:\n" + "\n".join(f"  {u}" for u in unread[:10]))
    for entries, stage in (("backbones", "features"), ("segmenters", "segments")):
        for entry in config[entries].values():
            # Kind-specific defaults (a DINOv2 layer, SAM thresholds, a trained model's
            # input size) from models/kinds.py, before the schema's: a kind's default of a
            # key every kind reads (a trained model's `resolution`) wins over the schema's.
            entry.update(with_defaults(stage, entry))
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
            f"config key 'targets' names datasets {short_repr(unknown, MAX_SHOWN)} that are not "
            f"configured; configured: {short_repr(sorted(config['datasets']), MAX_SHOWN)}"
        )
    return config


# Said after an error at a string where the schema expects another type: how a
# `--config` value reaches the config (Snakemake reads each `key=value` with YAML's base
# loader, which keeps every scalar inside a mapping or list a string).
CONFIG_STRING_HINT = (
    "; a string where the schema expects another type: Snakemake's --config keeps each "
    'value inside a mapping or list a string (--config "backbones={daisy: {batch_size: 4}}" '
    "sets batch_size to '4'), so write a list as [a, b] and give nested settings in a YAML "
    "file with --configfile"
)


def string_hint(error, schema: dict) -> str:
    """:data:`CONFIG_STRING_HINT` when ``error`` refused a string where the schema
    expects a mapping or a list, or a value whose strings, read as YAML, would be valid
    (``'4'`` for an integer, ``['160', '120']`` for a size); else nothing."""
    if not isinstance(error.schema, dict):
        return ""
    types = error.schema.get("type", [])
    if isinstance(error.instance, str) and {"object", "array"} & set(
        [types] if isinstance(types, str) else types
    ):
        return CONFIG_STRING_HINT
    value = _strings_read_as_yaml(error.instance)
    if value == error.instance:
        return ""
    # Against the part of the schema that refused it, its `$ref`s read in the whole.
    part = {**error.schema, "definitions": schema.get("definitions", {})}
    valid = not any(jsonschema.Draft202012Validator(part).iter_errors(value))
    return CONFIG_STRING_HINT if valid else ""


def _strings_read_as_yaml(value):
    """``value`` with each string, at any depth, that YAML reads as another scalar
    (a number, a boolean) replaced by it."""
    if isinstance(value, dict):
        return {k: _strings_read_as_yaml(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_strings_read_as_yaml(v) for v in value]
    if isinstance(value, str):
        try:
            read = yaml.safe_load(value)
        except yaml.YAMLError:
            return value
        return read if isinstance(read, (bool, int, float)) else value
    return value


def _dotted(path) -> str:
    return ".".join(str(p) for p in path) or "(top level)"


def _get(config, path: tuple):
    for part in path:
        config = config[part]
    return config


def _set(config, path: tuple, value) -> None:
    _get(config, path[:-1])[path[-1]] = value


def non_finite_numbers(config) -> list[tuple[tuple, float]]:
    """(path, value) of every NaN or infinite number in ``config``, at any depth. YAML
    reads ``.nan`` and ``.inf`` as numbers, and every bound the schema sets lets NaN
    through (it compares false), so a ``radius_m: .nan`` would reach a job that finds
    no positive without naming the key."""
    found, stack = [], [((), config)]
    while stack:
        path, value = stack.pop()
        if isinstance(value, float) and not math.isfinite(value):
            found.append((path, value))
        elif isinstance(value, dict):
            stack.extend(((*path, k), v) for k, v in value.items())
        elif isinstance(value, list):
            stack.extend(((*path, i), v) for i, v in enumerate(value))
    return sorted(found, key=lambda item: list(map(str, item[0])))


def integral_floats(config: dict, schema: dict) -> list[tuple]:
    """The paths of the integral floats (YAML ``8.0``) in ``config`` where ``schema``
    expects an integer, to be made integers before anything hashes them: JSON Schema
    takes ``8.0`` for an integer, so it validates, but it would hash to another store
    key than ``8`` and reach numpy as a float. A fraction (``8.5``) stays, for the
    schema to refuse naming the key. Found by validating against a schema whose
    integers exclude floats: each such type error (in a ``oneOf`` branch too) names
    one."""
    checker = jsonschema.Draft202012Validator.TYPE_CHECKER.redefine(
        "integer", lambda _, value: isinstance(value, int) and not isinstance(value, bool)
    )
    strict = jsonschema.validators.extend(jsonschema.Draft202012Validator, type_checker=checker)
    found: list[tuple] = []
    stack = list(strict(schema).iter_errors(config))
    while stack:
        error = stack.pop()
        types = [error.validator_value] if error.validator == "type" else []
        types = [t for v in types for t in ([v] if isinstance(v, str) else v)]
        if (
            "integer" in types
            and "number" not in types
            and isinstance(error.instance, float)
            and error.instance.is_integer()
        ):
            found.append(tuple(error.absolute_path))
        stack.extend(error.context)
    return list(dict.fromkeys(found))


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
                            f"config file {self.name}: key {short_repr(key, MAX_SHOWN)} is "
                            f"given twice in one mapping, on line {first[key]} and line "
                            f"{line}; YAML would keep only the second (merge the two into one)"
                        )
                    first[key] = line
                except TypeError:  # an unhashable key: the constructor names it
                    pass
        return super().construct_mapping(node, deep=deep)


def check_config_files(files=()) -> None:
    """Read each config file again, refusing a key given twice in one mapping, naming the
    file, the key and both lines: YAML lets a second ``datasets:`` block pasted below the
    first replace it without a word."""
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
    segmenters, aggregators, search indexes and re-rankers (:mod:`vprflow.models.kinds`,
    :mod:`vprflow.aggregation.aggregators`, :mod:`vprflow.search.indexes`,
    :data:`vprflow.evaluation.rerank.RERANKERS`),
    of ground-truth kinds (:data:`vprflow.data.ground_truth.KINDS`) and of published
    vocabularies (:data:`vprflow.aggregation.vocabularies.PUBLISHED`) as enums, every
    other enum from the constant its ``x-enum`` names (:func:`enum_values`), the kinds
    an ``x-kinds`` item ``"module:CONSTANT"`` names (the trained models'), the ground
    truth's, re-ranker's and search index's ``kind``/``index`` descriptions completed
    with each entry's ``description``, each
    re-ranker option's default and the kinds that read it from the
    :class:`~vprflow.evaluation.rerank.Reranker` entries, and each method section of
    :data:`METHOD_DEFAULT_SECTIONS` as a top-level key, a method key and a dataset
    ``defaults`` key (each a reference to the section's definition)."""

    schema = yaml.safe_load(Path(path).read_text())
    _fill_enums(schema, "#")
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
    # Each kind's line comes from its entry, so a kind added to the code is described.
    for entries, prop in (
        (KINDS, definitions["dataset"]["properties"]["ground_truth"]["properties"]["kind"]),
        (RERANKERS, definitions["reranker"]["properties"]["kind"]),
        (SEARCH_INDEXES, definitions["retrieval"]["properties"]["index"]),
    ):
        lines = "; ".join(f"{name} = {entry.description}" for name, entry in entries.items())
        prop["description"] = f"{prop['description']}: {lines}"
    _reranker_options(definitions["reranker"]["properties"])
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


def enum_values(reference: str | list[str]) -> list:
    """The values an ``x-enum`` names: ``"module:CONSTANT"`` (a module of
    :data:`ENUM_MODULES`; a tuple or list gives its items, a dict its keys, a string
    itself), or a list of such references, their values joined in order."""
    references = [reference] if isinstance(reference, str) else list(reference)
    values: list = []
    for ref in references:
        module, _, name = str(ref).partition(":")
        if module not in ENUM_MODULES or not name:
            raise ValueError(
                f"x-enum {ref!r} is not 'module:CONSTANT' of a module in ENUM_MODULES "
                f"{list(ENUM_MODULES)}"
            )
        constant = getattr(importlib.import_module(module), name, None)
        if isinstance(constant, str):
            values.append(constant)
        elif isinstance(constant, (tuple, list, dict)) and constant:
            values.extend(constant)
        else:
            raise ValueError(
                f"x-enum {ref!r} names {type(constant).__name__} {constant!r}, not a string, "
                "or a non-empty tuple, list or dict"
            )
    if len(set(values)) != len(values):
        raise ValueError(f"x-enum {reference!r} gives a value twice: {values}")
    return values


def _fill_enums(part, where: str) -> None:
    """Set the ``enum`` of every schema object with an ``x-enum``, and expand each
    ``"module:CONSTANT"`` item of an ``x-kinds`` into the kinds it names (``where``: its
    place in the schema, for an error)."""
    if isinstance(part, list):
        for index, item in enumerate(part):
            _fill_enums(item, f"{where}/{index}")
        return
    if not isinstance(part, dict):
        return
    if isinstance(part.get("x-kinds"), list) and any(":" in str(k) for k in part["x-kinds"]):
        # A kind list the code holds (the trained models' kinds) is named, not typed,
        # so that adding a trained model needs no schema change.
        try:
            part["x-kinds"] = [
                kind
                for item in part["x-kinds"]
                for kind in (enum_values(item) if ":" in str(item) else [item])
            ]
        except ValueError as error:
            raise ValueError(f"schema {where}: x-kinds: {error}") from None
    if "x-enum" in part:
        if "enum" in part:
            raise ValueError(f"schema {where}: both an enum and an x-enum; keep the x-enum")
        try:
            part["enum"] = enum_values(part["x-enum"])
        except ValueError as error:
            raise ValueError(f"schema {where}: {error}") from None
    for key, value in part.items():
        _fill_enums(value, f"{where}/{key}")


def _reranker_options(properties: dict) -> None:
    """Each re-ranker option's schema ``default`` and ``x-kinds`` (the kinds that read
    it), from the :data:`~vprflow.evaluation.rerank.RERANKERS` entries, which state them
    once: the schema file gives neither. Every option is filled into every entry,
    whatever its kind, so an option two kinds share must have one default."""
    defaults: dict = {}
    kinds: dict[str, list[str]] = {}
    for reranker in RERANKERS.values():
        for name, value in reranker.defaults.items():
            if name in defaults and defaults[name] != value:
                raise ValueError(
                    f"re-ranker option {name!r}: default {value!r} of {reranker.name!r} "
                    f"differs from {defaults[name]!r} of {kinds[name]}"
                )
            defaults[name] = value
            kinds.setdefault(name, []).append(reranker.name)
    for name, value in defaults.items():
        prop = properties.get(name)
        if prop is None:
            raise ValueError(
                f"re-ranker option {name!r} ({', '.join(kinds[name])}) has no property "
                "in the schema's reranker definition"
            )
        stated = sorted({"default", "x-kinds"} & set(prop))
        if stated:
            raise ValueError(
                f"schema reranker.{name} states {stated}: evaluation/rerank.py's RERANKERS does"
            )
        prop["default"] = value
        prop["x-kinds"] = kinds[name]


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
