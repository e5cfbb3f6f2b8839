"""The registry is what everything reads; the schema file and the registry must agree."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest
import yaml

from vprflow import registry
from vprflow.config import registry_enums, validate_config
from vprflow.plan import FORMAT_VERSIONS, build_plan

REPO = Path(__file__).resolve().parents[1]
SCHEMA_PATH = REPO / "workflow" / "schemas" / "config.schema.yaml"
SCHEMA = yaml.safe_load(SCHEMA_PATH.read_text())


def test_schema_enums_list_exactly_the_registry_components():
    enums = registry_enums(SCHEMA)
    assert enums["backbones"] == list(registry.BACKBONES)
    assert enums["segmenters"] == list(registry.SEGMENTERS)
    assert enums["aggregators"] == list(registry.AGGREGATORS)
    assert enums["search_indexes"] == list(registry.SEARCH_INDEXES)


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

    from vprflow.knn.exact import exact_knn

    # exact_knn's keyword defaults are read from the registry, never written again.
    keywords = inspect.signature(exact_knn).parameters
    for name, value in registry.SEARCH_INDEXES["exact_fast"].defaults.items():
        assert keywords[name].default == value, name


def test_config_readme_states_the_kind_and_search_index_defaults_from_the_registry():
    from vprflow.config import config_readme

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
        assert set(agg.needs) <= set(FORMAT_VERSIONS) - {"dataset", "features", "recall"}
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
    assert set(descriptors.inputs) == {"dataset", "features", *registry.AGGREGATORS[name].needs}


def _properties(schema: dict):
    yield from schema["properties"].items()
    for definition in schema["definitions"].values():
        for name, prop in definition.get("properties", {}).items():
            yield name, prop
            yield from prop.get("properties", {}).items()


def test_every_config_key_is_described_and_config_readme_is_current():
    from vprflow.config import config_readme

    undescribed = [name for name, prop in _properties(SCHEMA) if "description" not in prop]
    assert undescribed == []
    readme = (REPO / "config" / "README.md").read_text()
    assert readme == config_readme(SCHEMA), "run: python scripts/write_config_readme.py"


def test_method_sections_are_the_schema_method_sections():
    from vprflow.config import METHOD_DEFAULT_SECTIONS

    method = SCHEMA["definitions"]["method"]["properties"]
    sections = [name for name, prop in method.items() if "$ref" in prop]
    assert list(METHOD_DEFAULT_SECTIONS) == sections
    top = [name for name, prop in SCHEMA["properties"].items() if "$ref" in prop]
    # `figures` is the one top-level section that methods do not override.
    assert sorted(top) == sorted([*sections, "figures"])
