"""A preset's rows made otherwise than the published setting say how, in
results/published_<preset>.csv (vprflow.planning.published)."""

from __future__ import annotations

import copy
import csv

import numpy as np
import pytest
import yaml
from preset_miniatures import seventeen_places
from workflow_helpers import REPO, snakemake, write_config

from vprflow.planning.config import validate_config
from vprflow.planning.plan import build_plan
from vprflow.planning.published import published_changes, published_plan

SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"
SHIPPED = REPO / "config" / "config.yaml"
ROWS = ["segvlad", "anyloc_vlad"]  # the rows 17places' published rows name


def changes_of(raw: dict) -> dict:
    """The published table's changes for 17places under ``raw`` (its folder is absent:
    stages are planned without the images' contents, the same on both sides)."""
    plan = build_plan(validate_config(raw, SCHEMA))
    reference = published_plan(raw, SHIPPED, "17places", SCHEMA, {})
    return published_changes(plan, reference, "17places", ROWS)


@pytest.fixture
def shipped(tmp_path) -> dict:
    raw = yaml.safe_load(SHIPPED.read_text())
    raw["data_root"] = str(tmp_path / "data")
    raw["datasets"]["17places"] = {}
    return raw


def test_the_shipped_configs_preset_rows_are_made_as_published(shipped):
    assert changes_of(shipped) == {}


def test_daisy_features_name_the_features_vocabulary_pca_and_resolution_they_change(shipped):
    shipped["datasets"]["17places"] = {
        "resolution": [320, 240],
        "defaults": {"features": "daisy", "pca": {"dim": 128, "whiten": False}},
    }
    changes = changes_of(shipped)
    assert changes["segvlad"].split("; ") == [
        "features: backbone daisy (published: dinov2)",
        "pca: dim 128 (published: 1024), whiten false (published: true)",
        "segments: resolution 160 x 120 (published: 320 x 240)",
        "vocabulary: source map (published: published)",
    ]
    assert changes["anyloc_vlad"] == (
        "features: backbone daisy (published: dinov2); vocabulary: source map (published: "
        "published)"
    )


def test_a_component_edited_in_the_runs_config_is_named_against_the_shipped_one(shipped):
    shipped["backbones"]["dinov2_vitg14"]["layer"] = 20
    shipped["segmenters"]["sam_vith"]["points_per_side"] = 16
    changes = changes_of(shipped)
    assert changes["anyloc_vlad"].startswith("features: layer 20 (published: 31)")
    assert "segments: points_per_side 16 (published: 32)" in changes["segvlad"]


def test_a_method_option_of_the_run_is_named(shipped):
    shipped["methods"]["segvlad"] = {
        **shipped["methods"]["segvlad"],
        "segvlad": {"order": 1},
    }
    changes = changes_of(shipped)
    assert "descriptors: order 1 (published: 3)" in changes["segvlad"].split("; ")
    assert "anyloc_vlad" not in changes


@pytest.mark.workflow
def test_the_published_table_names_what_a_daisy_run_of_a_preset_changed(tmp_path):
    """17places run on DAISY at a small size (a miniature of its folder): each published
    row beside a row of this run says what differs (it used to say only `changed:
    resolution` beside DINOv2's number)."""
    seventeen_places(tmp_path / "data" / "17places", np.random.default_rng(0))
    config = yaml.safe_load(SHIPPED.read_text())
    config["data_root"] = str(tmp_path / "data")
    config["targets"] = []
    config["vocabulary"].update({"n_clusters": 4, "n_iter": 5})
    mine = {
        "resolution": [64, 48],
        "methods": ["anyloc_vlad"],
        "rerank": {},
        "defaults": {"features": "daisy"},
    }
    config["datasets"] = {"17places": mine}
    target = "results/published_17places.csv"
    snakemake(tmp_path, write_config(tmp_path, copy.deepcopy(config)), target)
    with open(tmp_path / target, newline="") as f:
        rows = {row["method"]: row for row in csv.DictReader(f)}
    anyloc = rows["AnyLoc-VLAD-DINOv2"]
    assert anyloc["row"] == "anyloc_vlad" and anyloc["recall@1"]
    assert anyloc["protocol"] == (
        "preset 17places, changed: resolution; not the published setting: features: "
        "backbone daisy (published: dinov2); vocabulary: source map (published: published)"
    )
    assert rows["SegVLAD-PreT (D, M)"]["recall@1"] == ""  # not run: nothing beside it


def test_a_rows_changes_follow_its_protocol_in_the_published_table():
    from vprflow.evaluation.published_rows import published_rows

    entry = {"method": "A", "paper": "P", "recall@1": 1.5, "recall@5": 2, "row": "anyloc_vlad"}
    ours = {"method": "anyloc_vlad", "recall@1": "0.5", "recall@5": "0.75", "protocol": "preset x"}
    changes = {"anyloc_vlad": "features: backbone daisy (published: dinov2)"}
    (row,) = published_rows([entry], [ours], changes)
    assert row["protocol"] == (
        "preset x; not the published setting: features: backbone daisy (published: dinov2)"
    )
    (row,) = published_rows([entry], [ours])
    assert row["protocol"] == "preset x"
