"""Dataset presets: every preset validates, joins a config as documented, reads its
miniature published layout with the published ground-truth rule, and (one Snakemake run
over every miniature) gives its recall table with no setting but the data."""

from __future__ import annotations

import csv
import logging
import re
from pathlib import Path

import numpy as np
import pytest
from preset_miniatures import MINIATURES, write_image
from script_helpers import load_script
from workflow_helpers import repo_config, scheduled_files, write_config, write_table

from vprflow.core.errors import ConfigError, DatasetError, PlanError
from vprflow.core.paths import CACHE, RECALL_CSV, store_path
from vprflow.data.datasets import list_dataset
from vprflow.data.ground_truth import ground_truth
from vprflow.data.presets import (
    _check_published_row,
    is_trained_method,
    merge_entry,
    presets,
    undefined_rows,
    unknown_dataset,
)
from vprflow.models.kinds import TRAINED_KINDS
from vprflow.planning.config import validate_config
from vprflow.planning.plan import build_plan

REPO = Path(__file__).resolve().parents[2]
SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"

datasets_doc = load_script("write_datasets_doc").datasets_doc


def config_with(data_root: Path, **changes) -> dict:
    config = repo_config()
    config["data_root"] = str(data_root)
    config.update(changes)
    return config


def test_every_preset_has_a_miniature_and_the_doc_is_current():
    assert list(MINIATURES) == list(presets())
    text = (REPO / "docs" / "datasets.md").read_text()
    assert text == datasets_doc(), "run: python scripts/write_datasets_doc.py"


def test_every_preset_validates_and_runs_methods_the_shipped_config_defines(tmp_path):
    config = config_with(tmp_path)
    config["datasets"].update({name: {} for name in presets()})
    datasets = validate_config(config, SCHEMA)["datasets"]
    for name in presets():
        assert datasets[name]["protocol"] == f"preset {name}"
        assert set(datasets[name]["methods"]) <= set(config["methods"]), name
        # A second protocol of one dataset reads the first one's folder.
        assert datasets[name]["path"] == name or datasets[name]["path"] in presets(), name


def test_a_preset_joins_when_its_folder_exists_or_the_config_names_it(tmp_path):
    names = lambda config: set(validate_config(config, SCHEMA)["datasets"])  # noqa: E731
    shipped = set(repo_config()["datasets"])
    assert names(config_with(tmp_path)) == shipped
    (tmp_path / "pitts30k").mkdir()
    assert names(config_with(tmp_path)) == shipped | {"pitts30k"}
    assert "baidu_mall" in names(config_with(tmp_path, targets=["baidu_mall"]))
    config = config_with(tmp_path)
    config["datasets"]["insideout"] = {"recall_at": [1, 5]}
    assert "insideout" in names(config)


def test_a_preset_found_by_its_folder_stays_out_of_a_config_that_cannot_run_it(tmp_path):
    (tmp_path / "pitts30k").mkdir()
    config = config_with(tmp_path)
    del config["rerankers"]["ransac_dinov2"]
    assert "pitts30k" not in validate_config(config, SCHEMA)["datasets"]
    assert "rerankers.ransac_dinov2" in unknown_dataset("pitts30k", validate_config(config, SCHEMA))
    del config["backbones"]["dinov2_vitg14"]
    assert "pitts30k" not in validate_config(config, SCHEMA)["datasets"]
    message = unknown_dataset("pitts30k", validate_config(config, SCHEMA))
    assert "backbones.dinov2_vitg14" in message and "datasets.pitts30k" in message


def test_a_config_entry_changes_only_the_keys_it_gives_and_the_table_says_which(tmp_path):
    config = config_with(tmp_path)
    config["datasets"]["pitts30k"] = {"ground_truth": {"radius": 10}, "recall_at": [1]}
    entry = validate_config(config, SCHEMA)["datasets"]["pitts30k"]
    assert entry["ground_truth"] == {"kind": "utm", "radius": 10}
    assert entry["reference"] == presets()["pitts30k"].dataset["reference"]
    assert entry["recall_at"] == [1]  # not a protocol key
    assert entry["protocol"] == "preset pitts30k, changed: ground_truth.radius"


def plan_of(config: dict, dataset: str) -> dict[str, list[dict]]:
    """Stage -> the params of the dataset's stages in the plan of ``config``."""
    plan = build_plan(validate_config(config, SCHEMA))
    return {
        stage: [s.record["params"] for s in stages.values() if s.dataset == dataset]
        for stage, stages in plan.stages.items()
    }


def test_features_a_user_swaps_in_take_the_presets_vocabulary_and_rerankers_along(tmp_path, capsys):
    """A user without weights runs a preset on DAISY: nothing of DINOv2-G is fetched or
    needed any more (the published vocabulary is 1,536-d DINOv2-G centres; the
    re-rankers match DINOv2-G features); the log says what followed."""
    config = config_with(tmp_path)
    config["datasets"]["pitts30k"] = {"defaults": {"features": "daisy", "segmenter": "slic"}}
    entry = validate_config(config, SCHEMA)["datasets"]["pitts30k"]
    assert "vocabulary" not in entry["defaults"]
    assert entry["rerank"] == {"anyloc_vlad": ["mnn", "ransac"], "segvlad": ["mnn", "ransac"]}
    stages = plan_of(config, "pitts30k")
    assert {s["source"] for s in stages["vocabulary"]} == {"map"}
    assert {s["backbone"] for s in stages["features"]} == {"daisy"}
    log = capsys.readouterr().err
    assert "published vocabulary 'urban'" in log and "datasets.pitts30k.defaults.vocabulary" in log
    assert "'mnn_dinov2' matches dinov2_vitg14's features, replaced by re-ranker 'mnn'" in log
    assert "datasets.pitts30k.defaults.pca" in log  # sized for DINOv2-G: said, not guessed


def test_a_swapped_in_feature_without_a_matching_reranker_drops_the_presets_reranking(
    tmp_path, capsys
):
    config = config_with(tmp_path)
    config["datasets"]["pitts30k"] = {"defaults": {"features": "dino_vitb8"}}
    entry = validate_config(config, SCHEMA)["datasets"]["pitts30k"]
    assert entry["rerank"] == {"anyloc_vlad": [], "segvlad": []}
    assert "replaced by nothing (dropped)" in capsys.readouterr().err
    # What the user gives is theirs: a vocabulary source and a rerank list stay.
    config["datasets"]["pitts30k"] = {
        "defaults": {"features": "daisy", "vocabulary": {"source": "map", "n_clusters": 8}},
        "rerank": {"anyloc_vlad": ["mnn"]},
    }
    entry = validate_config(config, SCHEMA)["datasets"]["pitts30k"]
    assert entry["defaults"]["vocabulary"]["n_clusters"] == 8
    assert entry["rerank"] == {"anyloc_vlad": ["mnn"], "segvlad": ["mnn", "ransac"]}


def test_a_redefined_backbone_entry_takes_the_presets_published_vocabulary_along(tmp_path, capsys):
    """The preset's features keep their entry name but are no longer DINOv2-G layer 31
    value features: the 1,536-d published centres cannot describe them."""
    (tmp_path / "pitts30k").mkdir()
    config = config_with(tmp_path)
    assert validate_config(config, SCHEMA)["datasets"]["pitts30k"]["defaults"]["vocabulary"] == {
        "source": "published",
        "name": "urban",
    }
    config["backbones"]["dinov2_vitg14"]["model"] = "facebook/dinov2-small"
    config["backbones"]["dinov2_vitg14"]["layer"] = 9
    entry = validate_config(config, SCHEMA)["datasets"]["pitts30k"]
    assert "vocabulary" not in entry["defaults"]
    assert entry["rerank"] == presets()["pitts30k"].dataset["rerank"]  # same entry name
    log = capsys.readouterr().err
    assert "backbones.dinov2_vitg14 (layer 9, model facebook/dinov2-small)" in log


def test_a_method_on_other_features_with_the_presets_vocabulary_stops_planning_naming_keys(
    tmp_path,
):
    """The published vocabulary would be fetched, the DINOv3 features computed, and only
    then would the vocabulary stage find 1,536 centres against 1,024-d features."""
    config = config_with(tmp_path)
    config["datasets"]["pitts30k"] = {"methods": ["anyloc_vlad_dinov3"]}
    with pytest.raises(PlanError) as error:
        validate_config(config, SCHEMA)
    message = str(error.value)
    assert "preset 'pitts30k'" in message and "'dinov3_vitl16'" in message
    assert "methods.anyloc_vlad_dinov3.vocabulary.source" in message
    assert "datasets.pitts30k.defaults.vocabulary" in message
    config["methods"]["anyloc_vlad_dinov3"]["vocabulary"] = {"source": "map"}
    assert validate_config(config, SCHEMA)["datasets"]["pitts30k"]["methods"]


FULL_ENTRY = {
    "path": "my_pitts",
    "reference": "db",
    "query": "q",
    "resolution": [320, 240],
    "ground_truth": {"kind": "utm", "radius": 25},
    "methods": ["anyloc_vlad"],
}


def test_a_full_entry_bearing_a_presets_name_is_merged_and_the_log_and_table_say_so(
    tmp_path, capsys
):
    config = config_with(tmp_path)
    config["datasets"]["pitts30k"] = dict(FULL_ENTRY)
    entry = validate_config(config, SCHEMA)["datasets"]["pitts30k"]
    assert entry["rerank"] == presets()["pitts30k"].dataset["rerank"]  # from the preset
    assert entry["protocol"].startswith("merged with preset pitts30k, changed: ")
    assert "preset" not in entry  # not a setting: no stage key holds it
    log = capsys.readouterr().err
    assert "datasets.pitts30k is a full entry" in log and "`preset: false`" in log


def test_preset_false_keeps_an_entry_of_a_presets_name_apart_from_the_preset(tmp_path):
    config = config_with(tmp_path)
    config["datasets"]["pitts30k"] = {**FULL_ENTRY, "preset": False}
    entry = validate_config(config, SCHEMA)["datasets"]["pitts30k"]
    assert entry["rerank"] == {} and "defaults" not in entry or not entry.get("defaults")
    assert entry["denominator"] == "with_positives" and entry["resolution"] == [320, 240]
    assert entry["protocol"] == "own entry (preset pitts30k not applied: preset: false)"
    assert "preset" not in entry
    # A partial entry with `preset: false` is no dataset: the schema names what is missing.
    config["datasets"]["pitts30k"] = {"recall_at": [1], "preset": False}
    with pytest.raises(ConfigError, match="pitts30k"):
        validate_config(config, SCHEMA)


def test_a_ground_truth_of_another_kind_replaces_the_presets_rule():
    merged = merge_entry(
        {"ground_truth": {"kind": "vprbench", "file": "gt.npy"}, "query": "q"},
        {"ground_truth": {"kind": "frame_window", "radius": 2}},
    )
    assert merged == {"ground_truth": {"kind": "frame_window", "radius": 2}, "query": "q"}


def test_a_vocabulary_of_another_source_replaces_the_presets_published_one():
    """A published vocabulary's `name` means nothing to a fitted one: kept, it would be
    a key the fitted vocabulary does not read."""
    merged = merge_entry(
        {"defaults": {"vocabulary": {"source": "published", "name": "urban"}}},
        {"defaults": {"vocabulary": {"source": "map", "n_clusters": 8}}},
    )
    assert merged == {"defaults": {"vocabulary": {"source": "map", "n_clusters": 8}}}


def test_an_absent_preset_says_where_it_belongs_where_to_get_it_and_its_layout(tmp_path):
    config = validate_config(config_with(tmp_path), SCHEMA)
    message = unknown_dataset("baidu_mall", config)
    assert str(tmp_path / "baidu_mall") in message
    assert presets()["baidu_mall"].dataset["source"] in message
    assert "training_gt/" in message and "query_images_undistort/" in message
    assert "presets:" in unknown_dataset("no_such_set", config)


def test_17places_is_the_segvlad_papers_protocol_and_17places_anyloc_is_anylocs():
    """The README's `results/recall_17places.csv` compares with the SegVLAD paper: +-15
    frames over queries with a positive; AnyLoc's +-2 frames file over all queries has
    its own name, and each published number sits under the protocol it was computed
    with."""
    seventeen, anyloc = presets()["17places"], presets()["17places_anyloc"]
    assert seventeen.dataset["ground_truth"] == {"kind": "frame_window", "radius": 15}
    assert seventeen.dataset["denominator"] == "with_positives"
    assert anyloc.dataset["ground_truth"]["file"] == "ground_truth_new.npy"
    assert anyloc.dataset["denominator"] == "all"
    assert anyloc.dataset["path"] == seventeen.dataset["path"] == "17places"
    assert {(p["recall@1"], p["recall@5"]) for p in seventeen.published} == {
        (95.3, 98.0),
        (95.3, 97.3),
    }
    assert [(p["recall@1"], p["recall@5"]) for p in anyloc.published] == [(65.0, 80.5)]
    row = next(line for line in datasets_doc().splitlines() if line.startswith("| `17places` |"))
    assert "frame_window:+-15" in row and "95.3 / 98.0" in row


def test_the_former_name_17places_pm15_says_where_its_protocol_went(tmp_path):
    config = config_with(tmp_path)
    config["datasets"]["17places_pm15"] = {"recall_at": [1]}
    with pytest.raises(ConfigError, match="renamed to '17places'.*'17places_anyloc'"):
        validate_config(config, SCHEMA)
    with pytest.raises(ConfigError, match="config key 'targets'.*renamed"):
        validate_config(config_with(tmp_path, targets=["17places_pm15"]), SCHEMA)
    message = unknown_dataset("17places_pm15", validate_config(config_with(tmp_path), SCHEMA))
    assert "renamed to '17places'" in message and "17places_anyloc" in message


def test_vp_air_anyloc_searches_the_distractors_and_counts_every_query(tmp_path):
    """AnyLoc's 66.7 were computed with the 10,000 distractors after the reference
    views in the database and every query counted; Revisit-Anything's 69.8 without
    them: two presets on one folder, each with its own published row."""
    MINIATURES["vp_air_anyloc"](tmp_path / "vp_air", np.random.default_rng(0))
    config = config_with(tmp_path, targets=["vp_air", "vp_air_anyloc"])
    datasets = validate_config(config, SCHEMA)["datasets"]
    plain = list_dataset(tmp_path, "vp_air", datasets["vp_air"])
    anyloc = list_dataset(tmp_path, "vp_air_anyloc", datasets["vp_air_anyloc"])
    distractors = sorted((tmp_path / "vp_air" / "distractors").iterdir())
    assert anyloc.reference == plain.reference + distractors
    assert anyloc.query == plain.query
    for name in ("vp_air", "vp_air_anyloc"):
        files = anyloc if name == "vp_air_anyloc" else plain
        truth = ground_truth(files, datasets[name]["ground_truth"], tmp_path / "vp_air")
        assert all(max(t) < len(plain.reference) for t in truth)
    assert datasets["vp_air_anyloc"]["denominator"] == "all"
    assert datasets["vp_air"]["denominator"] == "with_positives"
    assert [p["recall@1"] for p in presets()["vp_air_anyloc"].published] == [66.7]
    assert [p["recall@1"] for p in presets()["vp_air"].published] == [69.8]
    assert "printf" in presets()["vp_air_anyloc"].layout


def layout_error(data_root: Path, name: str) -> str:
    """The error of listing the preset ``name`` under ``data_root``."""
    dataset = validate_config(config_with(data_root, targets=[name]), SCHEMA)["datasets"][name]
    with pytest.raises(DatasetError) as error:
        list_dataset(data_root, name, dataset)
    return str(error.value)


def test_a_presets_layout_one_level_down_is_found_and_the_move_named(tmp_path):
    MINIATURES["pitts30k"](tmp_path / "pitts30k" / "pitts30k", np.random.default_rng(0))
    message = layout_error(tmp_path, "pitts30k")
    assert "images/test/database/   10,000 images" in message  # the expected tree
    assert f"one level down, in {tmp_path / 'pitts30k' / 'pitts30k'}" in message
    assert "mv pitts30k/* . && rmdir pitts30k" in message
    assert "datasets.pitts30k.path: pitts30k/pitts30k" in message


def test_the_downloaders_layout_where_the_authors_is_expected_says_how_to_convert(tmp_path):
    root = tmp_path / "amstertime"
    for role in ("database", "queries"):
        write_image(root / "images" / "test" / role / "0001.jpg", np.random.default_rng(0))
    message = layout_error(tmp_path, "amstertime")
    assert "new/                    1,231 present-day images" in message
    assert f"{root} holds VPR-datasets-downloader's layout" in message
    assert "`mv images/test/database new && mv images/test/queries old && rm -r images`" in message


def test_raw_msls_train_val_says_how_to_copy_the_kept_queries(tmp_path):
    root = tmp_path / "msls_sf"
    for role in ("database", "query"):
        write_image(root / "train_val" / "sf" / role / "images" / "a.jpg", np.random.default_rng(0))
    message = layout_error(tmp_path, "msls_sf")
    assert "holds MSLS as Mapillary ships it" in message
    assert "cp train_val/sf/database/images/* database/" in message
    assert "msls_val_qIdx.npy" in message and "'/sf/' in p" in message


def test_vp_air_anyloc_without_its_database_list_says_how_to_write_it(tmp_path):
    MINIATURES["vp_air"](tmp_path / "vp_air", np.random.default_rng(0))
    message = layout_error(tmp_path, "vp_air_anyloc")
    assert "reference list" in message and "database_with_distractors.txt" in message
    assert "`printf '%s\\n' reference_views/* distractors/* > database_with_distractors.txt`" in (
        message
    )


def test_a_preset_folder_in_no_known_layout_names_what_it_holds(tmp_path):
    (tmp_path / "sf_xl_val" / "photos").mkdir(parents=True)
    message = layout_error(tmp_path, "sf_xl_val")
    assert "holds photos/: neither that layout, nor it one level down" in message
    assert "CosPlace's SF-XL folders" in message  # the layouts it looked for


@pytest.mark.parametrize("name", list(MINIATURES))
def test_each_presets_ground_truth_is_the_published_rule_on_its_miniature(tmp_path, name):
    preset = presets()[name]
    expected = MINIATURES[name](tmp_path / preset.dataset["path"], np.random.default_rng(0))
    dataset = validate_config(config_with(tmp_path, targets=[name]), SCHEMA)["datasets"][name]
    files = list_dataset(tmp_path, name, dataset)
    truth = ground_truth(files, dataset["ground_truth"], tmp_path / dataset["path"])
    assert [q.name for q in files.query] and sorted(q.name for q in files.query) == sorted(expected)
    for query, positives in zip(files.query, truth, strict=True):
        assert {files.reference[i].name for i in positives} == expected[query.name], query
    assert any(len(t) for t in truth)


@pytest.mark.parametrize(("name", "city"), [("msls_sf", "sf"), ("msls_cph", "cph")])
def test_an_msls_city_query_with_positives_only_in_the_other_city_is_left_out_and_logged(
    tmp_path, caplog, name, city
):
    from vprflow.evaluation.recall import counted_queries, recall_at

    # The miniature's <city>q3 lists one positive, in the other city: Revisit-Anything's
    # city split leaves it none, and its calc_recall / get_recall do not count it.
    MINIATURES[name](tmp_path / name, np.random.default_rng(0))
    dataset = validate_config(config_with(tmp_path, targets=[name]), SCHEMA)["datasets"][name]
    files = list_dataset(tmp_path, name, dataset)
    with caplog.at_level("WARNING", logger="vprflow"):
        truth = ground_truth(files, dataset["ground_truth"], tmp_path / name)
    empty = [q.name for q, t in zip(files.query, truth, strict=True) if not len(t)]
    assert empty == [f"{city}q3.jpg"]
    assert (
        f"1 of the 3 kept {city} queries have their listed positives (msls_val_pIdx.npy) "
        f"only in the other city, so none after the city filter (e.g. {city}q3.jpg)"
    ) in caplog.text
    assert dataset["denominator"] == "with_positives"
    assert counted_queries(truth, dataset["denominator"]).sum() == 2
    # Every other query found at rank 1: the published Recall@1 is 1, not 2 / 3.
    ranking = np.array([[t[0] if len(t) else 0] for t in truth])
    assert recall_at(ranking, truth, [1], dataset["denominator"]) == {1: 1.0}


@pytest.mark.workflow
def test_every_presets_table_comes_from_its_data_alone(tmp_path, caplog):
    """Every miniature's table with no setting but its folder: the real Snakefile plans
    them all (a dry run), and the jobs it schedules run through the rules' own runners in
    this process (some 300 jobs; as Snakemake jobs they took three minutes, each one's
    start costing more than its work on a miniature). The models are swapped for the
    weight-free DAISY backbone at a small fixed size (not a protocol key), as a user
    without weights does, and only AnyLoc-VLAD runs, which keeps the run short: the
    published vocabulary and the DINOv2 re-rankers follow the swap (the config's
    vocabulary is fitted, `mnn` and `ransac` re-rank), so nothing is fetched and no
    DINOv2 is needed."""
    data = tmp_path / "data"
    for name, build in MINIATURES.items():
        build(data / presets()[name].dataset["path"], np.random.default_rng(1))
    config = config_with(data)
    config["backbones"]["daisy"]["resolution"] = [64, 48]
    config["vocabulary"] = {"n_clusters": 4, "n_iter": 5}
    # One preset keeps its (followed) re-rankers, to show its re-ranked rows; the others
    # turn them off (an empty list) to keep the run short.
    reranked = "pitts30k"
    for name in MINIATURES:
        config["datasets"][name] = {
            "methods": ["anyloc_vlad"],
            "defaults": {"features": "daisy", "segmenter": "slic"},
            **({} if name == reranked else {"rerank": {"anyloc_vlad": [], "segvlad": []}}),
        }
    path = write_config(tmp_path, config)
    targets = [RECALL_CSV.format(dataset=name) for name in MINIATURES]
    store = re.compile(rf"{CACHE}/[a-z_]+/[0-9a-f]{{16}}\.zarr")  # not a shard
    scheduled = {o for o in scheduled_files(tmp_path, path, *targets) if store.fullmatch(o)}
    plan = build_plan(validate_config(config, SCHEMA))
    done: dict = {}
    caplog.set_level(logging.INFO, logger="vprflow")
    for name in MINIATURES:
        write_table(plan, name, data, tmp_path, done)
    # What ran here is what the Snakefile schedules: every store, no other.
    assert {store_path(stage, key) for stage, key in done} == scheduled
    for name in MINIATURES:
        rows = list(csv.DictReader(open(tmp_path / RECALL_CSV.format(dataset=name))))
        expected = ["anyloc_vlad"]
        if name == reranked:
            expected += ["anyloc_vlad+mnn", "anyloc_vlad+ransac"]
        assert [r["method"] for r in rows] == expected, name
        assert rows[0]["protocol"] == f"preset {name}"
        assert 0 <= float(rows[0]["recall@1"]) <= 1
        if name.startswith("msls_"):
            # The city presets leave out <city>q3 (positives only in the other city);
            # msls_val counts every kept query.
            counted = ("6", "0") if name == "msls_val" else ("2", "1")
            assert (rows[0]["n_queries"], rows[0]["n_queries_without_positive"]) == counted
    for city in ("sf", "cph"):
        assert f"1 of the 3 kept {city} queries have their listed positives" in caplog.text


def trained_config(data_root: Path, **changes) -> dict:
    """config/trained.yaml over config/config.yaml, as Snakemake merges the two files
    (mappings key by key, a list replaced)."""
    import yaml

    from vprflow.planning.plan import deep_merge

    extra = yaml.safe_load((REPO / "config" / "trained.yaml").read_text())
    config = deep_merge(config_with(data_root), extra)
    config.update(changes)
    return config


def test_every_published_row_names_a_method_the_shipped_configs_define(tmp_path):
    config = trained_config(tmp_path)
    assert undefined_rows(set(config["methods"])) == []
    rows = [row for preset in presets().values() for row in preset.published]
    assert {r["row"] for r in rows if "row" in r} >= {"anyloc_vlad", "segvlad", "mixvpr"}
    # The SegVLAD-FineT rows need the authors' fine-tuned checkpoint: no row.
    assert all("row" not in r for r in rows if "FineT" in r["method"])
    # A method no config defines is named with its preset and row.
    messages = undefined_rows(set(config["methods"]) - {"mixvpr"})
    assert messages and all("'mixvpr'" in m for m in messages)
    assert any("'pitts30k'" in m and "'MixVPR (ResNet50, 4096)'" in m for m in messages)


def test_a_training_free_row_is_a_method_its_preset_runs_and_a_trained_row_one_it_appends(
    tmp_path,
):
    """A row's method appears in the preset's table: the training-free ones are in its
    own methods, the others are trained methods that `trained_baselines` appends."""
    config = trained_config(tmp_path)
    for name, preset in presets().items():
        for row in preset.published:
            if "row" in row and row["row"] not in preset.dataset["methods"]:
                assert is_trained_method(row["row"], config, TRAINED_KINDS), (name, row)
    assert not is_trained_method("segvlad", config, TRAINED_KINDS)
    # anyloc_vlad on SALAD's tokens
    assert is_trained_method("salad_tokens_vlad", config, TRAINED_KINDS)


def test_a_malformed_published_row_is_named_with_its_preset():
    with pytest.raises(ValueError, match=r"presets\.yaml: pitts30k: .*unknown \['rows'\]"):
        _check_published_row(
            "pitts30k",
            {"method": "m", "paper": "p", "recall@1": 1, "recall@5": 2, "rows": "mixvpr"},
        )
    with pytest.raises(ValueError, match="pitts30k.*row must be a method name"):
        _check_published_row(
            "pitts30k", {"method": "m", "paper": "p", "recall@1": 1, "recall@5": 2, "row": 3}
        )


def test_trained_baselines_appends_the_trained_rows_methods_to_each_preset_only(tmp_path):
    for name in ("pitts30k", "msls_val", "st_lucia"):
        (tmp_path / name).mkdir()
    config = trained_config(tmp_path)
    datasets = validate_config(config, SCHEMA)["datasets"]
    # In the published rows' order, after the preset's own methods.
    assert datasets["pitts30k"]["methods"] == [
        "anyloc_vlad", "segvlad", "mixvpr", "convap", "boq_resnet50", "boq_dinov2"
    ]  # fmt: skip
    assert datasets["msls_val"]["methods"] == [
        "anyloc_vlad", "segvlad", "mixvpr", "convap", "salad", "boq_resnet50", "boq_dinov2"
    ]  # fmt: skip
    assert datasets["st_lucia"]["protocol"] == "preset st_lucia"  # methods are no protocol
    # A non-preset dataset keeps its methods (config/trained.yaml's list for corridor).
    assert datasets["corridor"]["methods"] == config["datasets"]["corridor"]["methods"]
    # A method the entry lists already is not listed twice; the entry's own order stays.
    config["datasets"]["pitts30k"] = {"methods": ["boq_dinov2", "anyloc_vlad"]}
    methods = validate_config(config, SCHEMA)["datasets"]["pitts30k"]["methods"]
    assert methods == ["boq_dinov2", "anyloc_vlad", "mixvpr", "convap", "boq_resnet50"]
    # false (the default): the preset's methods alone, as without the key.
    config = trained_config(tmp_path, trained_baselines=False)
    off = validate_config(config, SCHEMA)["datasets"]
    del config["trained_baselines"]
    assert validate_config(config, SCHEMA)["datasets"] == off
    assert off["pitts30k"]["methods"] == presets()["pitts30k"].dataset["methods"]


def test_trained_baselines_without_the_trained_methods_names_config_trained_yaml(tmp_path):
    config = config_with(tmp_path, targets=["pitts30k"], trained_baselines=True)
    with pytest.raises(ConfigError) as error:
        validate_config(config, SCHEMA)
    message = str(error.value)
    assert "pitts30k" in message and "'mixvpr'" in message and "config/trained.yaml" in message
    # A preset whose rows name no trained method joins as before.
    config = config_with(tmp_path, targets=["baidu_mall"], trained_baselines=True)
    baidu = validate_config(config, SCHEMA)["datasets"]["baidu_mall"]
    assert baidu["methods"] == presets()["baidu_mall"].dataset["methods"]


def test_trained_baselines_plans_a_trained_row_on_a_preset(tmp_path):
    """The appended methods plan on the preset as on any dataset: one row each, on the
    preset's ground truth, with no vocabulary (the model's own descriptor)."""
    data = tmp_path / "data"
    MINIATURES["pitts30k"](data / "pitts30k", np.random.default_rng(0))
    config = trained_config(data, targets=["pitts30k"])
    filled = validate_config(config, SCHEMA)
    for entry in filled["backbones"].values():
        if entry.get("checkpoint"):
            path = tmp_path / entry["checkpoint"]
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(entry["checkpoint"].encode())
            entry["checkpoint"] = str(path)
    plan = build_plan(filled)
    rows = [run.method for run in plan.runs["pitts30k"]]
    assert {"mixvpr", "convap", "boq_resnet50", "boq_dinov2"} <= set(rows)
