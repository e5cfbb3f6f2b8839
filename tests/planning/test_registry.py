"""Each wing's component entries (model kinds and their loaders, aggregators, search
indexes, re-rankers) are what everything reads; the schema file and they must agree."""

from __future__ import annotations

import ast
import copy
import importlib
import inspect
import json
import sys
import textwrap
from pathlib import Path

import pytest
import yaml
from script_helpers import load_script

from vprflow.aggregation.aggregators import AGGREGATORS, Aggregator, aggregator, prefixed
from vprflow.core.lazy import LazyModule
from vprflow.evaluation import rerank
from vprflow.models import kinds, loaders
from vprflow.planning.config import (
    METHOD_DEFAULT_SECTIONS,
    ConfigError,
    load_schema,
    validate_config,
)
from vprflow.planning.plan import FORMAT_VERSIONS, build_plan
from vprflow.search import indexes

REPO = Path(__file__).resolve().parents[2]
SCHEMA_PATH = REPO / "workflow" / "schemas" / "config.schema.yaml"
SCHEMA = load_schema(SCHEMA_PATH)

config_readme = load_script("write_config_readme").config_readme


def test_a_component_name_outside_the_registry_is_refused_listing_the_registrys():
    raw = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    raw["methods"]["segvlad"]["aggregator"] = "softvlad"
    with pytest.raises(ConfigError, match="'softvlad' is not one of") as error:
        validate_config(raw, SCHEMA_PATH)
    assert str(list(AGGREGATORS)) in str(error.value)


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

    from vprflow.search.exact import exact_knn

    # Each index names its search function, whose keyword parameters are exactly the
    # index's parameters (plus device where it runs on a GPU), defaults read from the entry
    # (exact_fast's through the wrapper that imports torch only when it runs).
    for index in indexes.SEARCH_INDEXES.values():
        function = exact_knn if index.name == "exact_fast" else index.knn
        assert _lazy_imports_resolve(index.knn), index.name
        keywords = {
            name: p.default
            for name, p in inspect.signature(function).parameters.items()
            if p.kind is inspect.Parameter.KEYWORD_ONLY and name != "stats"
        }
        assert keywords.pop("device", None) == ("auto" if index.uses_gpu else None), index.name
        assert keywords == index.defaults, index.name


def test_exact_knn_takes_its_keyword_defaults_from_the_index_entry():
    import inspect

    from vprflow.search.exact import exact_knn

    # exact_knn's keyword defaults are read from search/defaults.py, never written again.
    keywords = inspect.signature(exact_knn).parameters
    for name, value in indexes.SEARCH_INDEXES["exact_fast"].defaults.items():
        assert keywords[name].default == value, name


def test_config_readme_states_the_kind_and_search_index_defaults_from_the_registry():
    readme = config_readme(SCHEMA)
    for index in indexes.SEARCH_INDEXES.values():
        for name, value in index.defaults.items():
            assert f"`{name}` (`{json.dumps(value)}`)" in readme, (index.name, name)
    assert (
        "| `layer` | integer | `31` (dinov2), `18` (dinov3), `-1` (dino), `3` (resnet50) |"
        in readme
    )
    assert "| `radius` | number, >= 0 | `25` (kind utm) |" in readme


@pytest.mark.parametrize(
    ("definition", "entries"), [("backbone", kinds.BACKBONES), ("segmenter", kinds.SEGMENTERS)]
)
def test_every_kind_default_is_a_schema_property(definition, entries):
    """A default a kind fills in must be a key a config entry may set."""
    properties = SCHEMA["definitions"][definition]["properties"]
    for kind in entries.values():
        assert set(kind.defaults) <= set(properties), kind.name


def test_model_kinds_that_read_weights_name_a_default_model_and_a_loader():
    for stage, entries in (("features", kinds.BACKBONES), ("segments", kinds.SEGMENTERS)):
        for kind in entries.values():
            if kind.weights == "model":
                assert kind.defaults.get("model"), kind.name
                assert kind.uses_gpu, kind.name
            # A kind loads a model (models/loaders.py names its loader) or reads a file.
            assert (kind.name not in loaders.LOADERS[stage]) == kind.reads_file, kind.name


def _lazy_calls(function) -> list:
    """The functions ``function`` reaches by a ``from module import name`` inside it or
    through a :func:`vprflow.core.lazy.lazy_import` module of its own module (a loader
    wrapper's ``vit.load_vit``); each must exist, or it would fail only when a workflow
    first runs it."""
    own = sys.modules[function.__module__]
    found = []
    for node in ast.walk(ast.parse(textwrap.dedent(inspect.getsource(function)))):
        if isinstance(node, ast.ImportFrom):
            module = importlib.import_module(node.module)
            found += [getattr(module, alias.name) for alias in node.names]
        elif (
            isinstance(node, ast.Attribute)
            and isinstance(node.value, ast.Name)
            and isinstance(getattr(own, node.value.id, None), LazyModule)
        ):
            found.append(getattr(getattr(own, node.value.id), node.attr))
    assert all(callable(f) for f in found), found
    return found


def _lazy_imports_resolve(function) -> bool:
    return bool(_lazy_calls(function)) or function.__module__ != loaders.__name__


def test_the_loaders_cover_every_kind_that_loads_a_model_and_each_import_resolves():
    for stage, kinds_of_stage in (("features", kinds.BACKBONES), ("segments", kinds.SEGMENTERS)):
        loaded = {n for n, k in kinds_of_stage.items() if not k.reads_file}
        assert set(loaders.LOADERS[stage]) == loaded, stage
        for name, loader in loaders.LOADERS[stage].items():
            assert loader.__module__.startswith("vprflow.models."), name
            assert _lazy_imports_resolve(loader), name
    assert set(loaders.TRAINED_MODELS) == set(kinds.TRAINED_KINDS)
    for name, loader in loaders.TRAINED_MODELS.items():
        assert _lazy_imports_resolve(loader), name


def test_a_kind_that_reads_a_file_has_no_model_to_load():
    with pytest.raises(ValueError, match="backbone 'import' reads a file"):
        loaders.load_model("features", {"backbone": "import", "file": "x.h5"})


def test_one_loader_serves_the_vit_kinds_and_one_the_sam_kinds_each_kind_named_once():
    from vprflow.models.sam.adapters import ADAPTERS, SAM_KINDS
    from vprflow.models.vit import VIT_FAMILIES

    vits = {n for n, k in kinds.BACKBONES.items() if isinstance(k.spec, kinds.VitFamily)}
    sams = {n for n, k in kinds.SEGMENTERS.items() if isinstance(k.spec, kinds.SamKind)}
    assert vits == set(VIT_FAMILIES) == {"dinov2", "dinov3", "dino"}
    assert sams == set(SAM_KINDS) == {"sam", "sam_hq", "sam2"}
    assert {loaders.LOADERS["features"][n] for n in vits} == {loaders._load_vit}
    assert {loaders.LOADERS["segments"][n] for n in sams} == {loaders._load_sam}
    for name in sams:
        spec = kinds.SEGMENTERS[name].spec
        assert SAM_KINDS[name] == (spec.model_class, ADAPTERS[spec.model_class]), name
        # The options its adapter takes are config keys the kind fills in.
        assert set(spec.adapter_options) <= set(kinds.SEGMENTERS[name].defaults), name


def _own_loader(wrapper):
    """The model module's loader that a models/loaders.py wrapper of TRAINED_MODELS calls
    (through the module's lazy import)."""
    (loader,) = _lazy_calls(wrapper)
    return loader


def test_each_trained_kind_has_a_loader_that_takes_its_variants_options():
    """What a trained kind's entry says of its files and input size its model module
    reads from it (nothing here lists the models: a new one edits no test); its loader
    must take each variant's options, and its defaults come from its entry."""
    assert set(loaders.TRAINED_MODELS) == set(kinds.TRAINED_KINDS)
    for name in kinds.TRAINED_KINDS:
        kind = kinds.BACKBONES[name]
        spec = kind.spec
        assert spec is kinds.trained_model(name), name
        assert loaders.LOADERS["features"][name] is loaders._load_trained, name
        loader = _own_loader(loaders.TRAINED_MODELS[name])
        assert loader.__module__.startswith("vprflow.models."), name
        for variant in spec.variants.values():
            assert set(variant.loader_options) <= set(inspect.signature(loader).parameters), name
        if spec.input_size is None:  # `own`, or the dataset's
            own = {"resolution": kinds.OWN_SIZE} if spec.own_size else {}
            assert {k: v for k, v in kind.defaults.items() if k == "resolution"} == own, name
        else:
            assert kind.defaults["resolution"] == list(spec.input_size), name
        assert kind.defaults["variant"] == spec.default_variant, name


def test_each_trained_kind_states_the_map_stride_and_input_size_of_its_architecture():
    """The entries' map strides and input sizes against the architectures themselves."""
    import torch

    from vprflow.models.trained import boq, convap, cosplace, mixvpr, netvlad
    from vprflow.models.trunks.dinov2 import VITB14
    from vprflow.models.trunks.resnet import LAYER_STRIDES

    # The ResNet models' maps: the default layer of their feature_map, at its stride.
    for name, model_class in (
        ("mixvpr", mixvpr.MixVPR),
        ("convap", convap.ConvAP),
        ("boq_resnet50", boq.BoQResNet),
        ("cosplace", cosplace.GeoLocalizationNet),
        ("eigenplaces", cosplace.GeoLocalizationNet),
    ):
        layer = inspect.signature(model_class.feature_map).parameters["layer"].default
        assert kinds.BACKBONES[name].spec.patch_size == LAYER_STRIDES[layer], name
    # MixVPR's mixers fix its input size: 400 positions of layer3, 320 x 320.
    assert mixvpr.MixVPR().input_size == kinds.trained_model("mixvpr").height_width
    assert kinds.BACKBONES["cosplace"].spec.default_variant == "ResNet50_2048"
    # The ImageNet ResNet-50 trunk: its layers' strides, layer3 by default (SNSM's).
    trunk = kinds.BACKBONES["resnet50"]
    assert {f"layer{k}": v for k, v in trunk.spec.layer_strides.items()} == LAYER_STRIDES
    assert trunk.defaults["layer"] == 3 and trunk.defaults["output"] == "features"
    assert not trunk.spec.descriptor
    # The maps' strides: VGG16 conv5_3 halves four times, DINOv2-B/14's patches are 14.
    trunk = netvlad.NetVLADModel(4, None).encoder
    assert trunk(torch.zeros(1, 3, 64, 48)).shape[-2:] == (64 // 16, 48 // 16)
    assert kinds.BACKBONES["netvlad"].spec.patch_size == 16
    assert VITB14["patch_size"] == 14
    for name in ("salad", "boq_dinov2", "megaloc", "vlad_buff"):
        assert kinds.BACKBONES[name].spec.patch_size == 14, name
    # The kinds whose evaluations read every image unresized; the schema offers their value.
    own = {n for n, k in kinds.BACKBONES.items() if k.defaults.get("resolution") == "own"}
    assert own == {"megaloc", "cosplace", "eigenplaces"}
    choices = SCHEMA["definitions"]["backbone"]["properties"]["resolution"]["oneOf"]
    assert {"const": kinds.OWN_SIZE} in choices


def test_schema_x_kinds_may_name_the_trained_kinds():
    # The trained kinds' keys name kinds.TRAINED_KINDS instead of listing them, so a
    # new trained model needs no schema change; loaded, they list every trained kind.
    raw = yaml.safe_load(SCHEMA_PATH.read_text())["definitions"]["backbone"]["properties"]
    loaded = SCHEMA["definitions"]["backbone"]["properties"]
    for key in ("checkpoint", "variant", "output"):
        assert "vprflow.models.kinds:TRAINED_KINDS" in raw[key]["x-kinds"], key
        assert set(kinds.TRAINED_KINDS) <= set(loaded[key]["x-kinds"]), key
    assert "dinov2" in loaded["checkpoint"]["x-kinds"]
    assert loaded["output"]["enum"] == list(kinds.TRAINED_OUTPUTS)


def test_a_kind_default_of_a_key_every_kind_reads_wins_over_the_schemas():
    """A trained model's `resolution` defaults to its published input size, not the
    schema's `dataset`; written, the entry's own value stays."""
    config = toy_config(aggregator="model", features="own")
    config["backbones"]["own"] = {"backbone": "netvlad"}
    config["backbones"]["given"] = {"backbone": "netvlad", "resolution": "dataset"}
    filled = validate_config(config, SCHEMA_PATH)["backbones"]
    assert filled["own"]["resolution"] == [640, 480]
    assert filled["given"]["resolution"] == "dataset"
    assert filled["own"]["output"] == "descriptor"
    assert filled["own"]["variant"] == "patchnetvlad-pitts30k-4096"
    assert filled["daisy"]["resolution"] == "dataset"


def test_every_reranker_names_a_score_function_taking_exactly_its_settings():
    import inspect

    from vprflow.evaluation.precision_recall import SCORE_KINDS

    for reranker in rerank.RERANKERS.values():
        function = reranker.scores
        keywords = {
            name
            for name, p in inspect.signature(function).parameters.items()
            if p.kind is inspect.Parameter.KEYWORD_ONLY
        }
        assert keywords == set(reranker.defaults) | set(reranker.fixed), reranker.name
        assert not set(reranker.defaults) & set(reranker.fixed), reranker.name
        assert reranker.score in SCORE_KINDS, reranker.name


def test_the_schema_takes_each_reranker_options_default_and_kinds_from_the_registry():
    raw = yaml.safe_load(SCHEMA_PATH.read_text())["definitions"]["reranker"]["properties"]
    loaded = SCHEMA["definitions"]["reranker"]["properties"]
    for reranker in rerank.RERANKERS.values():
        for name, value in reranker.defaults.items():
            assert "default" not in raw[name] and "x-kinds" not in raw[name], name
            assert loaded[name]["default"] == value, (reranker.name, name)
            assert reranker.name in loaded[name]["x-kinds"], (reranker.name, name)
    config = toy_config(aggregator="gem")
    config["rerankers"] = {"r": {"kind": "ransac", "features": "daisy"}}
    filled = validate_config(config, SCHEMA_PATH)["rerankers"]["r"]
    assert {k: filled[k] for k in rerank.RERANKERS["ransac"].options} == (
        rerank.RERANKERS["ransac"].defaults
    )


def test_a_schema_that_restates_a_reranker_default_is_refused_naming_it(tmp_path):
    raw = yaml.safe_load(SCHEMA_PATH.read_text())
    raw["definitions"]["reranker"]["properties"]["threshold"]["default"] = 1.5
    path = tmp_path / "schema.yaml"
    path.write_text(yaml.safe_dump(raw))
    with pytest.raises(ValueError, match=r"reranker\.threshold states \['default'\]"):
        load_schema(path)


def test_every_aggregator_needs_only_planned_stages_and_has_a_function():
    for agg in AGGREGATORS.values():
        assert set(agg.needs) <= set(FORMAT_VERSIONS) - {"images", "dataset", "features", "recall"}
        assert agg.output in ("global", "segments")
        assert agg.reads in ("features", "descriptor"), agg.name
        assert agg.compute.__module__ == "vprflow.aggregation.aggregators", agg.name
        inputs = {"masks", "image_size", "patch_size"} if "segments" in agg.needs else set()
        inputs |= {"centres"} if "vocabulary" in agg.needs else set()
        keywords = list(inspect.signature(agg.compute).parameters)
        assert keywords[:2] == ["grid", "options"], agg.name
        assert set(keywords[2:]) == inputs, agg.name


def test_unknown_components_are_refused_by_name():
    with pytest.raises(ValueError, match="unknown aggregator 'vlad2'"):
        aggregator("vlad2")
    with pytest.raises(ValueError, match="unknown backbone 'dinov4'"):
        kinds.model_kind("features", {"backbone": "dinov4"})


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


@pytest.mark.parametrize("name", sorted(AGGREGATORS))
def test_the_plan_builds_exactly_the_stages_an_aggregator_needs(name, tmp_path):
    from synthetic import make_dataset
    from workflow_helpers import toy_config

    make_dataset(tmp_path / "toy", n_places=3)
    config = toy_config(tmp_path, resolution=[64, 48], methods=["m"])
    config["methods"] = {"m": {"aggregator": name, "features": "daisy"}}
    if AGGREGATORS[name].reads == "descriptor":  # a trained model's (planned only)
        (tmp_path / "weights.ckpt").write_bytes(b"weights")
        config["backbones"]["own"] = {
            "backbone": "salad",
            "checkpoint": str(tmp_path / "weights.ckpt"),
        }
        config["methods"]["m"]["features"] = "own"
    plan = build_plan(validate_config(config, SCHEMA_PATH))
    (descriptors,) = plan.stages["descriptors"].values()
    assert set(descriptors.inputs) == {"images", "features", *AGGREGATORS[name].needs}


def _properties(schema: dict):
    yield from schema["properties"].items()
    for definition in schema["definitions"].values():
        for name, prop in definition.get("properties", {}).items():
            yield name, prop
            yield from prop.get("properties", {}).items()


def test_every_config_key_is_described_and_config_readme_is_current():
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


def test_every_kind_default_is_a_key_its_kind_reads_and_x_kinds_name_real_kinds():
    # One place (the schema's x-kinds) says which kind reads a key; the kinds'
    # defaults and re-ranker options must agree with it, or validation would refuse
    # what a kind fills in (or fill what it refuses).
    from vprflow.planning.config import kind_keys

    definitions = SCHEMA["definitions"]
    for entries, definition, kind_key in (
        (kinds.BACKBONES, definitions["backbone"], "backbone"),
        (kinds.SEGMENTERS, definitions["segmenter"], "segmenter"),
    ):
        keys = kind_keys(definition, kind_key)
        for kind in entries.values():
            assert set(kind.defaults) <= set(keys[kind.name]), kind.name
    keys = kind_keys(definitions["reranker"], "kind")
    common = {"kind", "features", "top_k"}
    for reranker in rerank.RERANKERS.values():
        assert set(keys[reranker.name]) == common | set(reranker.options), reranker.name
    truth = definitions["dataset"]["properties"]["ground_truth"]
    for definition, kind_key in (
        (definitions["backbone"], "backbone"),
        (definitions["segmenter"], "segmenter"),
        (definitions["reranker"], "kind"),
        (definitions["vocabulary"], "source"),
        (truth, "kind"),
    ):
        names = set(definition["properties"][kind_key]["enum"])
        for name, prop in definition["properties"].items():
            assert set(prop.get("x-kinds", names)) <= names, (kind_key, name)
    # A kind's `then` requires and defaults only keys the kind reads.
    truth_keys = kind_keys(truth, "kind")
    for part in truth["allOf"]:
        kind = part["if"]["properties"]["kind"]["const"]
        then = part["then"]
        named = set(then.get("required", [])) | set(then.get("properties", {}))
        assert named <= set(truth_keys[kind]), kind


def test_method_sections_are_derived_from_the_registry_in_their_old_order():
    # The order reaches the resolved settings and the tables: deriving the list from the
    # aggregators' `sections` must give the tuple it was written as.
    from vprflow.planning import config

    old = ("vocabulary", "vlad", "pca", "segvlad", "voting", "retrieval", "snsm", "pooling")
    assert config.SECTION_ORDER == old
    # The old tuple, then (after it) only sections of aggregators added since.
    assert METHOD_DEFAULT_SECTIONS[: len(old)] == old
    assert config.method_default_sections() == METHOD_DEFAULT_SECTIONS
    own = [s for agg in AGGREGATORS.values() for s in agg.sections]
    assert set(METHOD_DEFAULT_SECTIONS) == set(own) | set(config.SHARED_SECTIONS)
    added = tuple(s for s in dict.fromkeys(own) if s not in old)
    assert METHOD_DEFAULT_SECTIONS[len(old) :] == added


def test_a_new_aggregators_section_follows_the_others(monkeypatch):
    from vprflow.planning import config

    new = Aggregator("new", (), "global", _grid_sum, sections=("new_section",))
    monkeypatch.setitem(AGGREGATORS, new.name, new)
    assert config.method_default_sections() == (*METHOD_DEFAULT_SECTIONS, "new_section")


def test_an_aggregator_left_without_options_and_columns_reads_its_sections():
    method = {"vlad": {"a": 1, "b": 2}, "segvlad": {"order": 3}, "snsm": {"window": 5}}
    both = Aggregator("x", (), "global", _grid_sum, sections=("segvlad", "vlad"))
    assert both.options(method) == {"order": 3, "a": 1, "b": 2}
    assert both.columns(method) == {"segvlad.order": 3, "vlad.a": 1, "vlad.b": 2}
    # What the entries' written-out lambdas were before `sections`.
    for name, section in (("anyloc_vlad", "vlad"), ("snsm", "snsm")):
        agg = AGGREGATORS[name]
        assert agg.options(method) == dict(method[section])
        assert agg.columns(method) == prefixed(section, method[section])
    segvlad = AGGREGATORS["segvlad"]
    assert segvlad.columns(method) == {
        **prefixed("segvlad", method["segvlad"]),
        **prefixed("vlad", method["vlad"]),
    }
    model = AGGREGATORS["model"]
    assert (model.options(method), model.columns(method)) == ({}, {})


def _grid_sum(grid, options):
    return grid.sum(axis=(0, 1))
