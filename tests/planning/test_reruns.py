"""What a change reruns: the table of settings against the stages whose keys
they change, in docs/usage.md, and no model stage for a ground-truth change."""

from __future__ import annotations

import copy

import pytest
import yaml
from synthetic import make_dataset
from workflow_helpers import REPO, toy_config

from vprflow.planning import reruns
from vprflow.planning.config import validate_config
from vprflow.planning.plan import (
    FORMAT_VERSIONS,
    NOT_DATASET_STAGE,
    STAGES,
    TRUTH_SETTINGS,
    build_plan,
)

SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"
SHIPPED = REPO / "config" / "config.yaml"

EVERYTHING = tuple(STAGES)  # in the order data flows: images, dataset, features, ...
FROM_FEATURES = EVERYTHING[2:]
FROM_SEARCH = EVERYTHING[EVERYTHING.index("search") :]
TRUTH = ("dataset", "recall")

# setting -> the stages a change of it reruns (the design; docs/usage.md shows the same).
EXPECTED = {
    "ground_truth.radius (frame_window)": TRUTH,
    "ground_truth.kind": TRUTH,
    "ground_truth.kind (paired: true)": TRUTH,
    "ground_truth.file's content": TRUTH,
    "ground_truth.drop_out_of_range": TRUTH,
    "denominator": ("recall",),
    "recall_at (within the top 20)": ("recall",),
    "recall_at (past 20)": ("matches", "rerank", "recall"),  # the re-ranking is as deep as recall
    "paired": EVERYTHING,  # the queries' order
    "exif_orientation": EVERYTHING,
    "recursive": EVERYTHING,
    "follow_links": EVERYTHING,
    "an image's content": EVERYTHING,
    "resolution": FROM_FEATURES,
    "source": (),
    "data_root": (),
    "backbones.daisy.radius": ("features", *EVERYTHING[4:]),  # not segments
    "segmenters.slic.n_segments": ("segments", "pca", "descriptors", *FROM_SEARCH),
    "vocabulary.n_clusters": ("vocabulary", "pca", "descriptors", *FROM_SEARCH),
    "defaults.pca.dim": ("pca", "descriptors", *FROM_SEARCH),
    "voting.top_segments": FROM_SEARCH,
    # ransac's own pairs now (mnn keeps the top 100's); a scoring option keeps the pairs.
    "rerankers.ransac.top_k": ("matches", "rerank", "recall"),
    "rerankers.ransac.threshold": ("rerank", "recall"),
    "rerank": ("features", "matches", "rerank", "recall"),  # mnn_dinov2's features are new
    "pairs_depth": (),  # the pairs files rank past the recall from the stored retrieval
    "device": (),
    "shard_size": (),
    "descriptors_shard_size": (),
    "search_shard_size": (),
    "backbones.daisy.batch_size": (),
}


@pytest.fixture(scope="module")
def table() -> dict[str, tuple[str, ...]]:
    shipped = yaml.safe_load(SHIPPED.read_text())
    return {change.setting: stages for change, stages in reruns.rerun_table(shipped, SCHEMA)}


def test_each_setting_reruns_exactly_the_stages_the_table_expects(table):
    assert table == EXPECTED


def test_no_ground_truth_or_denominator_change_reruns_a_model_stage(table):
    truth_rows = [s for s in table if s.startswith("ground_truth") or s == "denominator"]
    assert len(truth_rows) == 6
    for setting in truth_rows:
        assert not set(table[setting]) & set(reruns.FITTED_STAGES), setting


def test_the_rerun_table_in_usage_md_is_the_one_the_plan_computes():
    text = (REPO / "docs" / "usage.md").read_text()
    table = reruns.reruns_doc(SHIPPED, SCHEMA)
    assert reruns.with_table(text, table) == text, "run: python scripts/write_reruns_doc.py"


def model_keys(config: dict) -> dict[str, set[str]]:
    plan = build_plan(validate_config(copy.deepcopy(config), SCHEMA))
    return {stage: set(plan.stages.get(stage, {})) for stage in reruns.FITTED_STAGES}


@pytest.mark.parametrize(
    ("before", "after"),
    [
        ({"kind": "frame_window", "radius": 2}, {"kind": "frame_window", "radius": 3}),
        ({"kind": "none"}, {"kind": "pairs"}),
        ({"kind": "vprbench", "file": "ground_truth_new.npy"}, "edit the file"),
    ],
)
def test_a_ground_truth_change_keeps_the_key_of_every_model_stage(tmp_path, before, after):
    make_dataset(tmp_path / "toy", n_places=3, width=32, height=24)
    config = toy_config(tmp_path, resolution=[32, 24], paired=True, ground_truth=before)
    config["datasets"]["toy"]["methods"] = ["segvlad", "anyloc_vlad", "gem"]
    config["datasets"]["toy"]["rerank"] = {"segvlad": ["mnn"]}
    keys = model_keys(config)
    truth_key = build_plan(validate_config(copy.deepcopy(config), SCHEMA)).dataset_keys["toy"]
    if after == "edit the file":
        path = tmp_path / "toy" / "ground_truth_new.npy"
        path.write_bytes(path.read_bytes() + b"\0")
    else:
        config["datasets"]["toy"]["ground_truth"] = after
    assert all(keys.values())
    assert model_keys(config) == keys
    assert build_plan(validate_config(config, SCHEMA)).dataset_keys["toy"] != truth_key


def test_the_settings_kept_out_of_the_images_key_are_dataset_settings_of_the_schema():
    schema = yaml.safe_load(SCHEMA.read_text())
    # `protocol`: a preset's, added by config.validate_config
    settings = set(schema["definitions"]["dataset"]["properties"]) | {"protocol"}
    assert set(TRUTH_SETTINGS) | set(NOT_DATASET_STAGE) <= settings
    assert not set(TRUTH_SETTINGS) & set(NOT_DATASET_STAGE)
    assert list(FORMAT_VERSIONS)[:2] == ["images", "dataset"]


def test_msls_lists_pick_the_images_so_its_city_is_in_the_images_key_and_its_rule_is_not(tmp_path):
    make_dataset(tmp_path / "toy", n_places=3, width=32, height=24)
    config = toy_config(tmp_path, resolution=[32, 24], ground_truth={"kind": "msls", "city": "sf"})
    plan = build_plan(validate_config(config, SCHEMA))
    (images,) = plan.stages["images"].values()
    (truth,) = plan.stages["dataset"].values()
    assert images.record["params"]["ground_truth"] == {"kind": "msls", "city": "sf"}
    assert truth.record["params"]["ground_truth"]["city"] == "sf"
    assert truth.inputs == {"images": ("images", images.key)}
