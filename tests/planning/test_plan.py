"""The plan: which parameters reach which stage keys, and what experiments share."""

from __future__ import annotations

import copy

import pytest
import yaml
from workflow_helpers import REPO

from vprflow.aggregation.aggregators import AGGREGATORS
from vprflow.core.errors import ConfigError, PlanError
from vprflow.planning.config import validate_config
from vprflow.planning.plan import build_plan, content_key
from vprflow.search.indexes import SEARCH_INDEXES

SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"


@pytest.fixture
def config() -> dict:
    """The shipped config, naming the 17places preset (its folder is absent here)."""
    raw = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    raw["datasets"]["17places"] = {}
    return validate_config(raw, SCHEMA)


def keys_of(config: dict, dataset: str = "corridor", method: str = "segvlad") -> dict[str, str]:
    """Stage -> key along one method's chain."""
    plan = build_plan(config)
    run = next(r for r in plan.runs[dataset] if r.method == method)
    keys = {"recall": run.recall_key}
    frontier = [("recall", run.recall_key)]
    while frontier:
        stage, key = frontier.pop()
        for upstream, upstream_key in plan.get(stage, key).inputs.values():
            keys[upstream] = upstream_key
            frontier.append((upstream, upstream_key))
    return keys


def changed_stages(before: dict, after: dict, method: str = "segvlad") -> set[str]:
    a, b = keys_of(before, method=method), keys_of(after, method=method)
    assert a.keys() == b.keys()
    return {stage for stage in a if a[stage] != b[stage]}


def test_keys_are_deterministic_and_order_independent():
    assert content_key({"a": 1, "b": [1, 2]}) == content_key({"b": [1, 2], "a": 1})
    assert content_key({"a": 1}) != content_key({"a": 2})
    assert len(content_key({})) == 16


def test_shipped_methods_share_features_segments_vocabulary_and_pca(config):
    plan = build_plan(config)
    corridor = [
        s for stages in plan.stages.values() for s in stages.values() if s.dataset == "corridor"
    ]
    count = {}
    for stage in corridor:
        count[stage.stage] = count.get(stage.stage, 0) + 1
    assert count == {
        "images": 1,
        "dataset": 1,
        "features": 1,
        "segments": 1,
        "vocabulary": 1,
        "pca": 2,  # one per neighbourhood order with PCA (segvlad_o0 and segvlad)
        "descriptors": 5,
        "search": 4,  # the four SegVLAD methods' segment lists
        # anyloc_vlad and segvlad re-ranked by mnn and ransac on the methods' own features:
        # one matches store per method, scored by each re-ranker
        "matches": 2,
        "rerank": 4,
        "recall": 9,
    }


def test_order_refits_pca_but_never_features_segments_or_vocabulary(config):
    # Published: one PCA per neighbourhood order, fitted at the method's own order.
    changed = copy.deepcopy(config)
    changed["segvlad"]["order"] = 2
    assert changed_stages(config, changed) == {"pca", "descriptors", "search", "recall"}
    pca = build_plan(changed).get("pca", keys_of(changed)["pca"])
    assert pca.record["params"]["fit_on"]["order"] == 2


def test_fixed_fit_order_keeps_pca_when_the_order_changes(config):
    fixed = copy.deepcopy(config)
    fixed["pca"]["fit_order"] = 3
    changed = copy.deepcopy(fixed)
    changed["segvlad"]["order"] = 2
    assert changed_stages(fixed, changed) == {"descriptors", "search", "recall"}
    # fit_order 3 is what `method` resolves to at the default order 3: same PCA store.
    assert keys_of(fixed)["pca"] == keys_of(config)["pca"]


@pytest.mark.parametrize(
    ("section", "name", "value", "reaches"),
    [
        ("vocabulary", "centres", "unit", {"vocabulary", "pca", "descriptors", "search", "recall"}),
        ("vlad", "normalize_descriptors", False, {"pca", "descriptors", "search", "recall"}),
        ("pca", "solver", "randomized", {"pca", "descriptors", "search", "recall"}),
        ("voting", "vote_ranking", "all_images", {"recall"}),
        ("voting", "top_segments", 20, {"search", "recall"}),
    ],
)
def test_published_default_options_reach_their_stages(config, section, name, value, reaches):
    changed = copy.deepcopy(config)
    changed[section][name] = value
    assert changed_stages(config, changed) == reaches


def test_pooling_normalization_reaches_only_pooling_descriptors(config):
    changed = copy.deepcopy(config)
    changed["pooling"]["normalization"] = "none"
    a, b = keys_of(config, "roadscene", "gem"), keys_of(changed, "roadscene", "gem")
    assert {stage for stage in a if a[stage] != b[stage]} == {"descriptors", "recall"}
    assert keys_of(config, "roadscene", "snsm") == keys_of(changed, "roadscene", "snsm")


def test_omitted_method_sections_take_the_schema_defaults(config):
    raw = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    for section in ("vocabulary", "vlad", "pca", "segvlad", "retrieval", "snsm", "pooling"):
        raw.pop(section, None)
    for entry in raw["backbones"].values():
        entry.pop("resize", None)
    filled = validate_config(raw, SCHEMA)
    for section in ("vocabulary", "vlad", "pca", "segvlad", "retrieval", "snsm", "pooling"):
        assert filled[section] == config[section], section
    assert filled["backbones"]["daisy"]["resize"] == "method"


def test_segmenter_reaches_segments_pca_descriptors_recall(config):
    changed = copy.deepcopy(config)
    changed["segmenters"]["slic"]["n_segments"] = 60
    assert changed_stages(config, changed) == {
        "segments",
        "pca",
        "descriptors",
        "search",
        "recall",
    }


def test_backbone_reaches_everything_but_the_dataset(config):
    changed = copy.deepcopy(config)
    changed["backbones"]["daisy"]["radius"] = 10
    assert changed_stages(config, changed) == {
        "features",
        "vocabulary",
        "pca",
        "descriptors",
        "search",
        "recall",
    }


def test_execution_settings_are_not_in_keys(config):
    changed = copy.deepcopy(config)
    changed["backbones"]["daisy"]["batch_size"] = 8
    changed["device"] = "cpu"
    changed["shard_size"] = 16
    changed["descriptors_shard_size"] = 5
    changed["search_shard_size"] = 3
    changed["data_root"] = "/somewhere/else"
    assert changed_stages(config, changed) == set()


def test_masks_layout_per_image_keys_the_segments_and_after_and_packed_is_its_absence(config):
    """per_image is another store from the segments on; ``packed`` given is the stores
    every key before the option hashed, so naming it changes nothing."""
    segmenter = config["methods"]["segvlad"].get("segmenter", config["segmenter"])
    packed, per_image = copy.deepcopy(config), copy.deepcopy(config)
    packed["segmenters"][segmenter]["masks_layout"] = "packed"
    per_image["segmenters"][segmenter]["masks_layout"] = "per_image"
    assert changed_stages(config, packed) == set()
    changed = changed_stages(config, per_image)
    assert "segments" in changed and not changed & {"images", "features", "vocabulary"}


def test_recall_at_reaches_only_recall(config):
    changed = copy.deepcopy(config)
    changed["datasets"]["corridor"]["recall_at"] = [1, 2, 3]
    assert changed_stages(config, changed) == {"recall"}


def test_snsm_parameters_reach_only_its_descriptors(config):
    changed = copy.deepcopy(config)
    changed["snsm"]["upscale"] = 5
    a = keys_of(config, "roadscene", "snsm")
    b = keys_of(changed, "roadscene", "snsm")
    assert {s for s in a if a[s] != b[s]} == {"descriptors", "recall"}
    # and its pooling baselines on the same dataset share its features
    assert keys_of(config, "roadscene", "gem")["features"] == a["features"]


def test_resize_method_follows_each_methods_published_reader(config):
    # One backbone entry (resize: method) read as SNSM's code reads (PIL bilinear) for
    # SNSM and its baselines, and as SegVLAD's and AnyLoc's (OpenCV) for theirs.
    plan = build_plan(config)
    resize = {}
    for method in ("snsm", "gem", "segvlad", "anyloc_vlad"):
        key = keys_of(config, "roadscene", method)["features"]
        resize[method] = plan.stages["features"][key].record["params"]["resize"]
    assert resize == {
        "snsm": "antialias",
        "gem": "antialias",
        "segvlad": "linear",
        "anyloc_vlad": "linear",
    }
    fixed = copy.deepcopy(config)
    fixed["backbones"]["daisy"]["resize"] = "linear"
    fixed["datasets"]["roadscene"]["exif_orientation"] = "apply"  # one reader for both
    assert (
        keys_of(fixed, "roadscene", "snsm")["features"]
        == keys_of(fixed, "roadscene", "segvlad")["features"]
    )


def test_exif_orientation_follows_each_methods_published_reader_unless_the_dataset_says(config):
    # cv2.imread (SegVLAD, AnyLoc) turns images as their EXIF tag says; SNSM's
    # PIL.Image.open(...).convert("RGB") and its baselines read the stored pixels.
    def orientations(config):
        plan = build_plan(config)
        found = {}
        for method in ("snsm", "gem", "segvlad", "anyloc_vlad"):
            keys = keys_of(config, "roadscene", method)
            for stage in ("features", "segments"):
                if stage in keys:
                    record = plan.stages[stage][keys[stage]].record
                    found[method, stage] = record["params"]["exif_orientation"]
        return found

    assert config["datasets"]["roadscene"]["exif_orientation"] == "method"
    assert orientations(config) == {
        ("snsm", "features"): "ignore",
        ("gem", "features"): "ignore",
        ("segvlad", "features"): "apply",
        ("segvlad", "segments"): "apply",  # masks on the pixels its features saw
        ("anyloc_vlad", "features"): "apply",
    }
    for setting in ("apply", "ignore"):
        explicit = copy.deepcopy(config)
        explicit["datasets"]["roadscene"]["exif_orientation"] = setting
        assert set(orientations(explicit).values()) == {setting}


def test_vocabulary_file_is_keyed_by_its_content(config, tmp_path):
    import numpy as np

    centres = tmp_path / "centres.npy"
    np.save(centres, np.eye(4, dtype=np.float32))
    with_file = copy.deepcopy(config)
    with_file["vocabulary"] = {"source": "file", "file": str(centres)}
    first = keys_of(with_file)["vocabulary"]
    np.save(centres, 2 * np.eye(4, dtype=np.float32))
    assert keys_of(with_file)["vocabulary"] != first


def test_missing_vocabulary_file_is_named(config, tmp_path):
    config["vocabulary"] = {"source": "file", "file": str(tmp_path / "nope.pt")}
    with pytest.raises(PlanError, match="nope.pt"):
        build_plan(config)


def test_a_method_row_of_an_unknown_dataset_names_the_dataset_and_the_datasets_there_are():
    from vprflow.planning.plan import Plan, method_run, method_stores

    plan = Plan(runs={"corridor": [], "roadscene": []})
    for ask in (method_run, method_stores):
        with pytest.raises(PlanError) as raised:
            ask(plan, "corridr", "anyloc_vlad")
        assert str(raised.value) == (
            "no dataset named 'corridr'; the datasets are: ['corridor', 'roadscene']"
        )
    with pytest.raises(PlanError, match=r"no method 'anylc_vlad' on dataset 'corridor'"):
        method_run(plan, "corridor", "anylc_vlad")


def test_unknown_method_backbone_and_segmenter_are_named(config):
    broken = copy.deepcopy(config)
    broken["datasets"]["corridor"]["methods"] = ["segvald"]
    with pytest.raises(PlanError, match="segvald"):
        build_plan(broken)
    broken = copy.deepcopy(config)
    broken["methods"]["segvlad"]["features"] = "dinov3"
    with pytest.raises(PlanError, match="dinov3"):
        build_plan(broken)
    broken = copy.deepcopy(config)
    broken["segmenter"] = "watershed"
    with pytest.raises(PlanError, match="watershed"):
        build_plan(broken)


@pytest.mark.parametrize(
    ("path", "value", "named"),
    [
        (("segvlad", "ordr"), 3, "ordr"),
        (("datasets", "corridor", "resolutoin"), [1, 2], "resolutoin"),
        (("pca", "dim"), "many", "pca.dim"),
        (("segvlad", "order"), 9, "segvlad.order"),
        (("device",), "tpu", "device"),
    ],
)
def test_schema_errors_name_the_key(config, path, value, named):
    broken = copy.deepcopy(config)
    target = broken
    for part in path[:-1]:
        target = target[part]
    target[path[-1]] = value
    with pytest.raises(ConfigError, match=named.replace(".", r"\.")):
        validate_config(broken, SCHEMA)


def test_csv_row_lists_the_parameters_that_shaped_it(config):
    plan = build_plan(config)
    rows = {r.method: r.row_params for r in plan.runs["corridor"]}
    assert rows["segvlad"]["segvlad.order"] == 3 and rows["segvlad_o0"]["segvlad.order"] == 0
    assert "segvlad.order" not in rows["anyloc_vlad"]
    assert "pca.dim" not in rows["segvlad_nopca"] and rows["segvlad_nopca"]["pca.enabled"] is False
    assert rows["anyloc_vlad"]["features.backbone"] == "daisy"


def test_dataset_defaults_sit_between_top_level_and_method(config):
    plan = build_plan(config)
    features = {s.dataset: s.record["params"] for s in plan.stages["features"].values()}
    assert features["17places"]["backbone"] == "dinov2" and features["17places"]["layer"] == 31
    assert features["17places"]["weights"] == "hf:facebook/dinov2-giant"
    assert features["corridor"]["backbone"] == "daisy"
    segments = {s.dataset: s.record["params"] for s in plan.stages["segments"].values()}
    assert (
        segments["17places"]["segmenter"] == "sam" and segments["corridor"]["segmenter"] == "slic"
    )
    # A method's own setting beats the dataset's default.
    config["methods"]["segvlad"]["features"] = "daisy"
    assert (
        keys_of(config, "17places", "segvlad")["features"]
        != keys_of(config, "17places", "anyloc_vlad")["features"]
    )


def test_local_model_weights_are_in_the_key(config, tmp_path):
    model = tmp_path / "model"
    model.mkdir()
    (model / "config.json").write_text("{}")
    (model / "model.safetensors").write_bytes(b"weights v1")
    config["backbones"]["dinov2_vitg14"]["model"] = str(model)
    memo: dict = {}
    first = build_plan(config, memo)
    (model / "model.safetensors").write_bytes(b"weights v2 (changed)")
    second = build_plan(config, memo)
    keys = [
        {s.key for s in p.stages["features"].values() if s.dataset == "17places"}
        for p in (first, second)
    ]
    assert keys[0] != keys[1]
    assert len(memo) == 2  # one content hash per version of the weights


def test_missing_local_model_names_the_config_key_and_both_remedies(config, tmp_path):
    missing = tmp_path / "no-such-dinov2"
    config["backbones"]["dinov2_vitg14"]["model"] = str(missing)
    with pytest.raises(PlanError) as error:
        build_plan(config)
    text = str(error.value)
    assert "backbones.dinov2_vitg14.model" in text and str(missing) in text
    assert "huggingface-cli download" in text and "local directory" in text


def test_ground_truth_kinds_require_their_keys(config):
    for kind, key in (("frame_window", "radius"), ("vprbench", "file")):
        broken = copy.deepcopy(config)
        broken["datasets"]["corridor"]["ground_truth"] = {"kind": kind}
        with pytest.raises(ConfigError, match=f"datasets.corridor.ground_truth.*'{key}'"):
            validate_config(broken, SCHEMA)


def test_resolution_below_one_patch_names_the_config_key(config):
    config["datasets"]["corridor"]["resolution"] = [4, 3]
    with pytest.raises(PlanError, match=r"datasets.corridor.resolution = \[4, 3\].*8-pixel"):
        build_plan(config)


def test_corrupt_fingerprints_cache_is_named_ignored_and_rewritten_atomically(tmp_path):
    from vprflow.planning.fingerprints import load_fingerprints, save_fingerprints

    path = tmp_path / "fingerprints.json"
    path.write_text('{"half": "writ')
    with pytest.warns(UserWarning, match=r"fingerprints\.json is unreadable.*rebuilt"):
        assert load_fingerprints(path) == {}
    save_fingerprints({"a": "b"}, path)
    assert load_fingerprints(path) == {"a": "b"}
    assert [p.name for p in tmp_path.iterdir()] == ["fingerprints.json"]  # no temporary left


@pytest.mark.parametrize(
    ("index", "searches", "gpu"), [("flat", 1, False), ("exact_fast", 1, True), ("hnsw", 2, False)]
)
def test_retrieval_index_plans_its_search_and_an_exact_one_when_approximate(
    config, index, searches, gpu
):
    changed = copy.deepcopy(config)
    changed["retrieval"]["index"] = index
    plan = build_plan(changed)
    recall = plan.get("recall", keys_of(changed)["recall"])
    assert len({"search", "exact_search"} & set(recall.inputs)) == searches
    search = plan.get(*recall.inputs["search"])
    assert search.record["params"]["index"] == index
    assert search.run_params["uses_gpu"] is gpu
    if searches == 2:
        assert plan.get(*recall.inputs["exact_search"]).record["params"]["index"] == "flat"


# ------------------------------------------------------------------ defaults in keys


def test_the_dataset_stage_lists_images_as_the_plan_did(tmp_path):
    from PIL import Image
    from synthetic import make_dataset
    from workflow_helpers import toy_config

    from vprflow.data.datasets import list_dataset

    make_dataset(tmp_path / "toy", n_places=3)
    extra = tmp_path / "toy" / "query" / "extra"
    extra.mkdir()
    Image.new("RGB", (96, 72), (10, 20, 30)).save(extra / "x.png")
    config = validate_config(toy_config(tmp_path, recursive=False), SCHEMA)
    plan = build_plan(config)
    (dataset,) = plan.stages["images"].values()
    assert dataset.record["params"]["contents"] is not None
    # The stage lists from its hashed params alone; the plan listed from the config.
    spec = config["datasets"]["toy"]
    as_stage = list_dataset(tmp_path, "toy", dataset.record["params"])
    assert as_stage == list_dataset(tmp_path, "toy", spec)
    assert extra / "x.png" not in as_stage.query


def test_nested_defaults_are_filled_and_overrides_stay_partial(config):
    # Defaults inside a dataset's ground truth and download, by ground-truth kind.
    assert config["datasets"]["corridor"]["ground_truth"]["drop_out_of_range"] is False
    assert "source" not in config["datasets"]["corridor"]["ground_truth"]
    raw = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    del raw["datasets"]["corridor"]["download"]["strip"]
    raw["datasets"]["walk"] = {
        **raw["datasets"]["corridor"],
        "ground_truth": {"kind": "coordinates", "file": "gps.csv", "radius_m": 25},
    }
    filled = validate_config(raw, SCHEMA)
    assert filled["datasets"]["corridor"]["download"]["strip"] == 0
    assert filled["datasets"]["walk"]["ground_truth"]["source"] == "file"
    assert "drop_out_of_range" not in filled["datasets"]["walk"]["ground_truth"]
    # A method's sections and a dataset's `defaults` are merged over the filled top-level
    # ones: filling them would undo the dataset's defaults.
    assert filled["methods"]["segvlad_nopca"]["pca"] == {"enabled": False}
    assert filled["datasets"]["corridor"]["defaults"] == {"pca": {"dim": 128, "whiten": False}}


def test_the_utm_radius_default_is_the_schemas_and_reaches_the_dataset_key(config, tmp_path):
    schema = yaml.safe_load(SCHEMA.read_text())
    (utm,) = [
        part["then"]["properties"]["radius"]["default"]
        for part in schema["definitions"]["dataset"]["properties"]["ground_truth"]["allOf"]
        if part["if"]["properties"]["kind"] == {"const": "utm"}
    ]
    raw = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    raw["datasets"]["corridor"]["ground_truth"] = {"kind": "utm"}
    assert validate_config(raw, SCHEMA)["datasets"]["corridor"]["ground_truth"]["radius"] == utm
    for part in schema["definitions"]["dataset"]["properties"]["ground_truth"]["allOf"]:
        if part["if"]["properties"]["kind"] == {"const": "utm"}:
            part["then"]["properties"]["radius"]["default"] = utm + 5
    other = tmp_path / "schema.yaml"
    other.write_text(yaml.safe_dump(schema))
    changed = validate_config(raw, other)
    assert changed["datasets"]["corridor"]["ground_truth"]["radius"] == utm + 5
    plan = build_plan(validate_config(raw, SCHEMA))
    assert build_plan(changed).dataset_keys["corridor"] != plan.dataset_keys["corridor"]


def test_a_planned_stage_missing_a_filled_setting_fails_with_key_error(config):
    # Planning reads settings, it does not restate their defaults.
    del config["backbones"]["daisy"]["batch_size"]
    with pytest.raises(KeyError, match="batch_size"):
        build_plan(config)


def search_stages(config: dict) -> dict[str, str]:
    """``search`` (and ``exact_search`` when the index is approximate) -> key, of segvlad
    on corridor, with the descriptors key they search."""
    plan = build_plan(config)
    recall = plan.get("recall", keys_of(config)["recall"])
    return {name: key for name, (_, key) in recall.inputs.items() if name != "dataset"}


@pytest.mark.parametrize("index", sorted(SEARCH_INDEXES))
def test_the_planned_search_params_contain_every_default_of_the_index(config, index):
    config["retrieval"]["index"] = index
    plan = build_plan(config)
    search = plan.get("search", search_stages(config)["search"])
    assert search.record["params"]["params"] == SEARCH_INDEXES[index].defaults


def test_changing_an_index_default_changes_the_search_key_and_nothing_upstream(config, monkeypatch):
    config["retrieval"]["index"] = "hnsw"
    before = search_stages(config)
    monkeypatch.setitem(SEARCH_INDEXES["hnsw"].defaults, "ef_search", 64)
    after = search_stages(config)
    assert before["search"] != after["search"]
    assert before["exact_search"] == after["exact_search"]
    assert before["descriptors"] == after["descriptors"]


def test_an_index_default_written_out_gives_the_same_key_as_left_out(config):
    config["retrieval"] = {"index": "ivf_flat", "params": {}}
    left_out = search_stages(config)
    config["retrieval"]["params"] = dict(SEARCH_INDEXES["ivf_flat"].defaults)
    assert search_stages(config) == left_out


def test_a_parameter_the_index_does_not_take_is_refused_when_planning(config):
    config["methods"]["segvlad"]["retrieval"] = {"index": "hnsw", "params": {"nprobe": 8}}
    with pytest.raises(PlanError, match=r"method 'segvlad'.*\['nprobe'\].*index 'hnsw'"):
        build_plan(config)


def test_native_resolution_plans_the_images_own_size_and_the_stage_refuses_another(tmp_path):
    from PIL import Image
    from synthetic import make_dataset
    from workflow_helpers import toy_config

    from vprflow.core.errors import DatasetError
    from vprflow.stages.dataset import build_images
    from vprflow.stages.jobs import Job

    make_dataset(tmp_path / "toy", n_places=3, width=80, height=60)
    native = validate_config(toy_config(tmp_path, resolution="native"), SCHEMA)
    sized = validate_config(toy_config(tmp_path, resolution=[80, 60]), SCHEMA)

    def resolutions(config):
        plan = build_plan(config)
        return {
            stage: [s.record["params"]["resolution"] for s in plan.stages[stage].values()]
            for stage in ("features", "segments")
        }

    assert (
        resolutions(native)
        == resolutions(sized)
        == {
            "features": [[80, 60]],
            "segments": [[40, 30]],
        }
    )
    assert native["datasets"]["toy"]["resolution"] == "native"  # the caller's config as given
    (stage,) = build_plan(native).stages["images"].values()
    assert stage.record["params"]["native_size"] == [80, 60]
    build_images(Job(stage.record, {}, str(tmp_path / "ok.zarr"), data_root=str(tmp_path)))

    Image.new("RGB", (60, 80)).save(tmp_path / "toy" / "query" / "zz_portrait.png")
    (stage,) = build_plan(native).stages["images"].values()
    with pytest.raises(DatasetError, match=r"zz_portrait\.png is 60 x 80.*resolution: \[width"):
        build_images(Job(stage.record, {}, str(tmp_path / "bad.zarr"), data_root=str(tmp_path)))
    assert not (tmp_path / "bad.zarr").exists()


def test_a_reranker_setting_changes_only_its_rerank_and_the_reranked_recall(config):
    changed = copy.deepcopy(config)
    changed["rerankers"]["mnn"]["min_similarity"] = 0.5
    # A scoring option: the pairs (the matches store) are kept.
    assert changed_stages(config, changed, method="segvlad+mnn") == {"rerank", "recall"}
    assert changed_stages(config, changed, method="segvlad+ransac") == set()
    assert changed_stages(config, changed, method="segvlad") == set()
    # Another backbone's features: only the re-ranker's features and what follows change.
    changed["rerankers"]["mnn"]["features"] = "dino_vitb8"
    stages = changed_stages(config, changed, method="segvlad+mnn")
    assert stages == {"matches", "rerank", "recall"}  # (keys_of: one key per stage name)
    plan = build_plan(changed)
    run = next(r for r in plan.runs["corridor"] if r.method == "segvlad+mnn")
    rerank = plan.get(*plan.get("recall", run.recall_key).inputs["rerank"])
    features = plan.get(*plan.get(*rerank.inputs["matches"]).inputs["features"])
    assert features.record["params"]["backbone"] == "dino"


def test_a_preset_reranks_only_the_methods_a_config_keeps_and_a_typo_is_named():
    raw = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    raw["datasets"]["17places"] = {"methods": ["anyloc_vlad"]}
    config = validate_config(raw, SCHEMA)
    plan = build_plan(config)
    assert [r.method for r in plan.runs["17places"]] == [
        "anyloc_vlad",
        "anyloc_vlad+mnn_dinov2",
        "anyloc_vlad+ransac_dinov2",
    ]
    # A cluster GPU for re-ranking on a model's features, none for DAISY's.
    for dataset, method, gpu in (
        ("17places", "anyloc_vlad+mnn_dinov2", True),
        ("corridor", "anyloc_vlad+mnn", False),
    ):
        run = next(r for r in plan.runs[dataset] if r.method == method)
        rerank = plan.get(*plan.get("recall", run.recall_key).inputs["rerank"])
        matches = plan.get(*rerank.inputs["matches"])
        assert matches.run_params["uses_gpu"] is gpu, method
        assert rerank.run_params["uses_gpu"] is False, method  # scoring is CPU work
    config["datasets"]["corridor"]["rerank"] = {"segvald": ["mnn"]}
    with pytest.raises(PlanError, match=r"datasets\.corridor\.rerank names \['segvald'\]"):
        build_plan(config)
    config["datasets"]["corridor"]["rerank"] = {"segvlad": ["mmn"]}
    with pytest.raises(PlanError, match=r"names re-ranker 'mmn'.*rerankers"):
        build_plan(config)


def test_a_preset_override_of_a_key_its_ground_truth_kind_does_not_read_is_an_error():
    # pitts30k's truth is utm (radius 25): `radius_m` used to be ignored while the
    # protocol column said `changed: ground_truth.radius_m`.
    raw = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    raw["datasets"]["pitts30k"] = {"ground_truth": {"kind": "utm", "radius_m": 5}}
    with pytest.raises(ConfigError) as error:
        validate_config(raw, SCHEMA)
    message = str(error.value)
    assert "datasets.pitts30k.ground_truth.radius_m" in message
    assert "kind 'utm' does not read 'radius_m'; its keys: kind, radius" in message
    raw["datasets"]["pitts30k"] = {"ground_truth": {"radius": 5}}
    entry = validate_config(raw, SCHEMA)["datasets"]["pitts30k"]
    assert entry["ground_truth"]["radius"] == 5
    assert entry["protocol"] == "preset pitts30k, changed: ground_truth.radius"


def test_a_rerankers_features_naming_no_backbone_blames_the_reranker_entry(config):
    config["rerankers"]["mnn"]["features"] = "daisyy"
    with pytest.raises(PlanError) as error:
        build_plan(config)
    message = str(error.value)
    assert message.startswith("config key rerankers.mnn.features = 'daisyy' names no entry")
    assert "re-ranker 'mnn'" in message


def test_the_rerank_stage_retrieves_as_deep_as_the_recall_reads(config):
    plan = build_plan(config)
    run = next(r for r in plan.runs["corridor"] if r.method == "anyloc_vlad+mnn")
    recall = plan.get("recall", run.recall_key)
    rerank = plan.get("rerank", recall.inputs["rerank"][1])
    matches = plan.get(*rerank.inputs["matches"])
    assert matches.record["params"]["depth"] == recall.record["params"]["depth"] == 20


def test_the_rerankers_of_a_method_on_the_same_features_and_top_k_share_one_matches_store():
    """Shipped corridor: anyloc_vlad and segvlad each re-ranked by mnn and ransac on
    DAISY, top 100: one matches store per method, holding what decides the candidates
    and their pairs (not the re-ranker's kind or options); each rerank reads only it."""
    config = validate_config(yaml.safe_load((REPO / "config" / "config.yaml").read_text()), SCHEMA)
    plan = build_plan(config)
    runs = {r.method: r for r in plan.runs["corridor"]}
    for method in ("anyloc_vlad", "segvlad"):
        reranks = [
            plan.get(*plan.get("recall", runs[f"{method}+{r}"].recall_key).inputs["rerank"])
            for r in ("mnn", "ransac")
        ]
        assert [r.record["params"]["kind"] for r in reranks] == ["mnn", "ransac"]
        assert all(set(r.inputs) == {"matches"} for r in reranks)
        assert reranks[0].inputs["matches"] == reranks[1].inputs["matches"], method
        matches = plan.get(*reranks[0].inputs["matches"])
        recall = plan.get("recall", runs[method].recall_key)
        assert set(matches.record["params"]) == (
            {"top_k", "depth", "vote_ranking"} if method == "segvlad" else {"top_k", "depth"}
        )
        assert matches.record["params"]["top_k"] == 100
        retrieval = {k: v for k, v in recall.inputs.items() if k not in ("dataset", "exact_search")}
        assert {k: v for k, v in matches.inputs.items() if k not in ("images", "features")} == (
            retrieval
        )
    # Another top_k for ransac alone: its own matches store, mnn's kept.
    config["rerankers"]["ransac"]["top_k"] = 50
    before, after = (
        {k for k, s in p.stages["matches"].items() if s.dataset == "corridor"}
        for p in (plan, build_plan(config))
    )
    assert len(before) == 2 and len(after) == 4 and before < after


def test_a_config_with_its_keys_in_another_order_gives_records_of_the_same_repr(config):
    # Snakemake reruns a job whose params' repr changed: a config rewritten with sorted
    # keys (or edited into another order) must not rerun a stage whose key it keeps.
    def reordered(value):
        if isinstance(value, dict):
            return {k: reordered(value[k]) for k in reversed(list(value))}
        return value

    plan, other = build_plan(config), build_plan(reordered(config))
    records = {
        s: {k: repr(v.record) for k, v in stages.items()} for s, stages in plan.stages.items()
    }
    assert records == {
        s: {k: repr(v.record) for k, v in stages.items()} for s, stages in other.stages.items()
    }


def test_the_stages_an_aggregator_may_need_are_planned_as_the_table_of_stages_says(
    config, monkeypatch
):
    """Between features and descriptors the plan plans only what STAGES gives a planner:
    the same table the stage versions, runners and sharding come from."""
    from dataclasses import replace

    from vprflow.planning import plan

    assert {name for name, stage in plan.STAGES.items() if stage.needed} == {
        "segments",
        "vocabulary",
        "pca",
    }
    for needs in AGGREGATORS["segvlad"].needs:
        assert plan.STAGES[needs].needed is not None
    monkeypatch.setitem(plan.STAGES, "pca", replace(plan.STAGES["pca"], needed=None))
    with pytest.raises(PlanError, match="aggregator 'segvlad' needs unknown stage 'pca'"):
        build_plan(config)


def _with_trained(tmp_path, **entries) -> dict:
    """The shipped config, validated, with backbone entries of trained kinds (name ->
    entry, each given a checkpoint file in ``tmp_path``) and a method ``<name>_m`` per
    entry on corridor: aggregator ``model`` for a descriptor, ``anyloc_vlad`` for dense
    features."""
    raw = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    for name, entry in entries.items():
        path = tmp_path / f"{name}.ckpt"
        path.write_bytes(name.encode())
        raw["backbones"][name] = {"checkpoint": str(path), **entry}
        dense = entry.get("output") == "features"
        raw["methods"][f"{name}_m"] = {
            "aggregator": "anyloc_vlad" if dense else "model",
            "features": name,
        }
        raw["datasets"]["corridor"]["methods"].append(f"{name}_m")
    return validate_config(raw, SCHEMA)


def test_a_trained_models_descriptor_is_read_as_its_published_pipeline_reads(tmp_path):
    """Under aggregator ``model`` the features stage reads as the model's evaluation
    does (PIL: EXIF ignored, antialiased resize to the published input size; MegaLoc at
    the images' own size); under ``output: features`` the map is read as its method's
    pipeline reads (AnyLoc: OpenCV, EXIF applied)."""
    filled = _with_trained(
        tmp_path,
        salad={"backbone": "salad"},
        netvlad={"backbone": "netvlad"},
        megaloc={"backbone": "megaloc"},
        tokens={"backbone": "salad", "output": "features"},
    )
    plan = build_plan(filled)
    params = {
        name: plan.stages["features"][keys_of(filled, method=f"{name}_m")["features"]].record[
            "params"
        ]
        for name in ("salad", "netvlad", "megaloc", "tokens")
    }
    read = {n: (p["resolution"], p["resize"], p["exif_orientation"]) for n, p in params.items()}
    assert read == {
        "salad": ([322, 322], "antialias", "ignore"),
        "netvlad": ([640, 480], "antialias", "ignore"),
        "megaloc": ("own", "antialias", "ignore"),  # each image at its own size
        "tokens": ([322, 322], "linear", "apply"),
    }
    # A global method: its recall searches its descriptors, no segment search.
    keys = keys_of(filled, method="salad_m")
    assert set(keys) == {"images", "dataset", "features", "descriptors", "recall"}
    descriptors = plan.get("descriptors", keys["descriptors"])
    assert descriptors.record["params"] == {"aggregator": "model"}


def test_boqs_descriptor_is_read_with_torchvisions_bicubic_and_its_tokens_as_their_method_reads(
    tmp_path,
):
    filled = _with_trained(
        tmp_path,
        boq={"backbone": "boq_dinov2"},
        boq50={"backbone": "boq_resnet50"},
        boq_tokens={"backbone": "boq_dinov2", "output": "features"},
    )
    plan = build_plan(filled)
    read = {}
    for name in ("boq", "boq50", "boq_tokens"):
        key = keys_of(filled, method=f"{name}_m")["features"]
        params = plan.stages["features"][key].record["params"]
        read[name] = (params["resolution"], params["resize"])
    assert read == {
        "boq": ([322, 322], "bicubic_antialias"),
        "boq50": ([384, 384], "bicubic_antialias"),
        "boq_tokens": ([322, 322], "linear"),  # AnyLoc's reader, as every dense map
    }


def test_a_trained_models_variant_and_checkpoint_reach_its_features_and_everything_after(
    tmp_path,
):
    filled = _with_trained(tmp_path, netvlad={"backbone": "netvlad"})
    other = copy.deepcopy(filled)
    other["backbones"]["netvlad"]["variant"] = "patchnetvlad-pitts30k-512"
    after = {"features", "descriptors", "recall"}
    assert changed_stages(filled, other, method="netvlad_m") == after
    before = keys_of(filled, method="netvlad_m")
    (tmp_path / "netvlad.ckpt").write_bytes(b"retrained")  # same path, other weights
    retrained = keys_of(filled, method="netvlad_m")
    assert {stage for stage in before if before[stage] != retrained[stage]} == after


def test_a_trained_method_is_reranked_on_the_rerankers_dense_features(tmp_path):
    filled = _with_trained(tmp_path, salad={"backbone": "salad"})
    filled["datasets"]["corridor"]["rerank"]["salad_m"] = ["mnn"]
    plan = build_plan(filled)
    run = next(r for r in plan.runs["corridor"] if r.method == "salad_m+mnn")
    rerank = plan.get(*plan.get("recall", run.recall_key).inputs["rerank"])
    features = plan.get(*plan.get(*rerank.inputs["matches"]).inputs["features"])
    assert features.record["params"]["backbone"] == "daisy"
    assert run.row_params["aggregator"] == "model"
