"""The registry is what everything reads; the schema file and the registry must agree."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest
import yaml

from vprflow.core import registry
from vprflow.planning.config import (
    METHOD_DEFAULT_SECTIONS,
    ConfigError,
    load_schema,
    validate_config,
)
from vprflow.planning.plan import FORMAT_VERSIONS, build_plan

REPO = Path(__file__).resolve().parents[1]
SCHEMA_PATH = REPO / "workflow" / "schemas" / "config.schema.yaml"
SCHEMA = load_schema(SCHEMA_PATH)


def test_a_component_name_outside_the_registry_is_refused_listing_the_registrys():
    raw = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    raw["methods"]["segvlad"]["aggregator"] = "softvlad"
    with pytest.raises(ConfigError, match="'softvlad' is not one of") as error:
        validate_config(raw, SCHEMA_PATH)
    assert str(list(registry.AGGREGATORS)) in str(error.value)


def test_the_schema_file_does_not_restate_what_the_code_lists():
    # Component names, ground-truth kinds and method sections come from the code
    # (config.load_schema): a second copy in the file could only drift.
    raw = yaml.safe_load(SCHEMA_PATH.read_text())
    definitions = raw["definitions"]
    for definition, key in (
        (definitions["backbone"], "backbone"),
        (definitions["segmenter"], "segmenter"),
        (definitions["method"], "aggregator"),
        (definitions["retrieval"], "index"),
        (definitions["dataset"]["properties"]["ground_truth"], "kind"),
    ):
        assert "enum" not in definition["properties"][key], key
    sections = set(METHOD_DEFAULT_SECTIONS)
    assert not sections & set(raw["properties"])
    assert not sections & set(definitions["method"]["properties"])
    assert not sections & set(definitions["dataset"]["properties"]["defaults"]["properties"])


def test_every_search_index_is_one_the_search_stage_can_run():
    import inspect

    # Each index names its search function, whose keyword parameters are exactly the
    # index's parameters (plus device where it runs on a GPU), defaults read from the entry.
    for index in registry.SEARCH_INDEXES.values():
        function = registry.resolve(index.knn)
        keywords = {
            name: p.default
            for name, p in inspect.signature(function).parameters.items()
            if p.kind is inspect.Parameter.KEYWORD_ONLY and name != "stats"
        }
        assert keywords.pop("device", None) == ("auto" if index.uses_gpu else None), index.name
        assert keywords == index.defaults, index.name


def test_exact_knn_takes_its_keyword_defaults_from_the_registry_entry():
    import inspect

    from vprflow.search.exact import exact_knn

    # exact_knn's keyword defaults are read from the registry, never written again.
    keywords = inspect.signature(exact_knn).parameters
    for name, value in registry.SEARCH_INDEXES["exact_fast"].defaults.items():
        assert keywords[name].default == value, name


def test_config_readme_states_the_kind_and_search_index_defaults_from_the_registry():
    from vprflow.planning.config import config_readme

    readme = config_readme(SCHEMA)
    for index in registry.SEARCH_INDEXES.values():
        for name, value in index.defaults.items():
            assert f"`{name}` (`{json.dumps(value)}`)" in readme, (index.name, name)
    assert "| `layer` | integer | `31` (dinov2), `18` (dinov3), `-1` (dino) |" in readme
    assert "| `radius` | number, >= 0 | `25` (kind utm) |" in readme


@pytest.mark.parametrize(
    ("definition", "kinds"), [("backbone", registry.BACKBONES), ("segmenter", registry.SEGMENTERS)]
)
def test_every_kind_default_is_a_schema_property(definition, kinds):
    """A default the registry fills in must be a key a config entry may set."""
    properties = SCHEMA["definitions"][definition]["properties"]
    for kind in kinds.values():
        assert set(kind.defaults) <= set(properties), kind.name


def test_model_kinds_that_read_weights_name_a_default_model_and_a_loader():
    for kinds in (registry.BACKBONES, registry.SEGMENTERS):
        for kind in kinds.values():
            if kind.weights == "model":
                assert kind.defaults.get("model"), kind.name
                assert kind.uses_gpu, kind.name
            if kind.loader is not None:
                assert callable(registry.resolve(kind.loader)), kind.name
            else:
                assert kind.weights == "file", kind.name


def test_every_aggregator_needs_only_planned_stages_and_has_a_function():
    for agg in registry.AGGREGATORS.values():
        assert set(agg.needs) <= set(FORMAT_VERSIONS) - {"images", "dataset", "features", "recall"}
        assert agg.output in ("global", "segments")
        assert callable(registry.resolve(agg.image_descriptor)), agg.name


def test_unknown_components_are_refused_by_name():
    with pytest.raises(ValueError, match="unknown aggregator 'vlad2'"):
        registry.aggregator("vlad2")
    with pytest.raises(ValueError, match="unknown backbone 'dinov4'"):
        registry.model_kind("features", {"backbone": "dinov4"})


def toy_config(**method) -> dict:
    config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    config["datasets"] = {}
    config["targets"] = []
    config["methods"] = {"m": method}
    return config


def test_defaults_are_filled_before_hashing_so_keys_record_what_ran():
    """Leaving a kind default out or writing it gives the same key; a different value
    a different one."""
    config = toy_config(aggregator="gem")
    config["backbones"]["vit"] = {"backbone": "dinov2"}
    explicit = copy.deepcopy(config)
    explicit["backbones"]["vit"]["layer"] = 31
    other = copy.deepcopy(config)
    other["backbones"]["vit"]["layer"] = 30
    filled = validate_config(config, SCHEMA_PATH)
    assert filled["backbones"]["vit"]["layer"] == 31
    assert filled["backbones"]["vit"]["model"] == "facebook/dinov2-giant"
    assert filled == validate_config(explicit, SCHEMA_PATH)
    assert filled != validate_config(other, SCHEMA_PATH)


@pytest.mark.parametrize("name", sorted(registry.AGGREGATORS))
def test_the_plan_builds_exactly_the_stages_an_aggregator_needs(name, tmp_path):
    from synthetic import make_dataset
    from workflow_helpers import toy_config

    make_dataset(tmp_path / "toy", n_places=3)
    config = toy_config(tmp_path, resolution=[64, 48], methods=["m"])
    config["methods"] = {"m": {"aggregator": name, "features": "daisy"}}
    plan = build_plan(validate_config(config, SCHEMA_PATH))
    (descriptors,) = plan.stages["descriptors"].values()
    assert set(descriptors.inputs) == {"images", "features", *registry.AGGREGATORS[name].needs}


def _properties(schema: dict):
    yield from schema["properties"].items()
    for definition in schema["definitions"].values():
        for name, prop in definition.get("properties", {}).items():
            yield name, prop
            yield from prop.get("properties", {}).items()


def test_every_config_key_is_described_and_config_readme_is_current():
    from vprflow.planning.config import config_readme

    undescribed = [name for name, prop in _properties(SCHEMA) if "description" not in prop]
    assert undescribed == []
    readme = (REPO / "config" / "README.md").read_text()
    # The file as it is, or as committed: a user's own (uncommitted) datasets in it do not
    # fail the suite, while CI, on a clean clone, compares the shipped file itself.
    from workflow_helpers import committed_config, repo_config

    candidates = [repo_config(), committed_config()]
    matches = [c for c in candidates if c is not None and readme == config_readme(SCHEMA, c)]
    assert matches, "run: python scripts/write_config_readme.py"
    shipped = matches[0]
    # Every shipped backbone, segmenter and method is listed by name.
    for section in ("backbones", "segmenters", "methods", "rerankers"):
        for name in shipped[section]:
            assert f"| `{name}` |" in readme, (section, name)


def test_every_method_section_is_a_default_a_dataset_default_and_a_method_override():
    from vprflow.planning.plan import resolve_method

    raw = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    method = raw["methods"]["segvlad"]
    dataset = raw["datasets"]["corridor"]
    for section in METHOD_DEFAULT_SECTIONS:
        raw.setdefault(section, {})
        dataset.setdefault("defaults", {}).setdefault(section, {})
        method.setdefault(section, {})
    config = validate_config(raw, SCHEMA_PATH)
    settings = resolve_method(config, "segvlad", config["datasets"]["corridor"])
    assert set(METHOD_DEFAULT_SECTIONS) <= set(settings)
    # `figures` is the one top-level section that methods do not override.
    top = [name for name, prop in SCHEMA["properties"].items() if "$ref" in prop]
    assert sorted(top) == sorted([*METHOD_DEFAULT_SECTIONS, "figures"])


def test_every_registry_default_is_a_key_its_kind_reads_and_x_kinds_name_real_kinds():
    # One place (the schema's x-kinds) says which kind reads a key; the registry's kind
    # defaults and re-ranker options must agree with it, or validation would refuse
    # what a kind fills in (or fill what it refuses).
    from vprflow.planning.config import kind_keys

    definitions = SCHEMA["definitions"]
    for kinds, definition, kind_key in (
        (registry.BACKBONES, definitions["backbone"], "backbone"),
        (registry.SEGMENTERS, definitions["segmenter"], "segmenter"),
    ):
        keys = kind_keys(definition, kind_key)
        for kind in kinds.values():
            assert set(kind.defaults) <= set(keys[kind.name]), kind.name
    keys = kind_keys(definitions["reranker"], "kind")
    common = {"kind", "features", "top_k"}
    for reranker in registry.RERANKERS.values():
        assert set(keys[reranker.name]) == common | set(reranker.options), reranker.name
    truth = definitions["dataset"]["properties"]["ground_truth"]
    for definition, kind_key in (
        (definitions["backbone"], "backbone"),
        (definitions["segmenter"], "segmenter"),
        (definitions["reranker"], "kind"),
        (definitions["vocabulary"], "source"),
        (truth, "kind"),
    ):
        kinds = set(definition["properties"][kind_key]["enum"])
        for name, prop in definition["properties"].items():
            assert set(prop.get("x-kinds", kinds)) <= kinds, (kind_key, name)
    # A kind's `then` requires and defaults only keys the kind reads.
    truth_keys = kind_keys(truth, "kind")
    for part in truth["allOf"]:
        kind = part["if"]["properties"]["kind"]["const"]
        then = part["then"]
        named = set(then.get("required", [])) | set(then.get("properties", {}))
        assert named <= set(truth_keys[kind]), kind
