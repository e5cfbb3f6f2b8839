"""The report's tables on disk: which datasets' tables a failure withdraws, clearing the
withdrawn copies a good run supersedes, and a report that would lack items."""

from __future__ import annotations

import copy
from types import SimpleNamespace

import pytest
import yaml
from workflow_helpers import REPO

from vprflow.core.errors import ConfigError
from vprflow.planning.config import validate_config
from vprflow.planning.plan import MethodRun, build_plan, planning_failure
from vprflow.planning.reports import (
    clear_superseded,
    closing_lines,
    failed_datasets,
    report_error,
    report_gaps,
    stale_reports,
)

SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"


def test_a_good_run_clears_the_withdrawn_copy_of_a_table_it_wrote_again(tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    (results / "recall_a.csv").write_text("fresh")
    (results / "recall_a.csv.stale").write_text("withdrawn")
    (results / "recall_b.csv.stale").write_text("withdrawn, b not rebuilt")
    cleared = clear_superseded(str(tmp_path) + "/")
    assert cleared == [results / "recall_a.csv.stale"]
    assert (results / "recall_a.csv").read_text() == "fresh"
    assert (results / "recall_b.csv.stale").exists()


def test_a_good_run_ends_by_naming_its_tables_and_the_report_command(tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    (results / "recall_a.csv").write_text("table")
    (results / "predictions_a.csv").write_text("table")
    plan = SimpleNamespace(runs={"a": [], "b": []})  # b has no table on disk
    lines = closing_lines(plan, str(tmp_path) + "/")
    assert lines[0] == "vprflow: a: results/recall_a.csv, results/predictions_a.csv"
    assert "snakemake --report report.html" in lines[1] and len(lines) == 2


def test_a_run_asked_for_one_dataset_ends_by_naming_only_its_tables(tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    for name in ("a", "b"):
        (results / f"recall_{name}.csv").write_text("table")
    plan = SimpleNamespace(runs={"a": [], "b": []})
    lines = closing_lines(plan, str(tmp_path) + "/", ["b"])
    assert lines[0] == "vprflow: b: results/recall_b.csv" and len(lines) == 2


def shipped_config(**extra_datasets) -> dict:
    """The shipped config, with datasets laid out as corridor (no download) but for the
    keys given (name -> keys)."""
    raw = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    corridor = {k: v for k, v in raw["datasets"]["corridor"].items() if k != "download"}
    for name, keys in extra_datasets.items():
        raw["datasets"][name] = copy.deepcopy(corridor) | {"path": name, **keys}
    return raw


def test_a_config_that_does_not_validate_withdraws_no_table():
    raw = shipped_config()
    raw["targets"] = ["corridr"]
    with pytest.raises(ConfigError, match="corridr") as caught:
        validate_config(raw, SCHEMA)
    assert planning_failure(caught.value) is None
    assert failed_datasets(caught.value, {"datasets": {}}, ["corridor"]) == []


def test_a_dataset_that_cannot_be_planned_withdraws_its_own_tables_only_if_asked_for():
    config = validate_config(shipped_config(alley={"methods": ["segvald"], "rerank": {}}), SCHEMA)
    with pytest.raises(Exception, match="segvald") as caught:
        build_plan(config)
    assert failed_datasets(caught.value, config, ["corridor"]) == []
    assert failed_datasets(caught.value, config, ["alley", "corridor"]) == ["alley"]


def test_a_method_that_cannot_be_planned_withdraws_every_asked_for_dataset_listing_it(
    tmp_path,
):
    raw = shipped_config(alley={"methods": ["anyloc_vlad", "mine"], "rerank": {}})
    raw["backbones"]["mine"] = {"backbone": "dinov2", "model": str(tmp_path / "no-model")}
    raw["methods"]["mine"] = {"aggregator": "anyloc_vlad", "features": "mine"}
    raw["datasets"]["corridor"]["methods"].append("mine")
    config = validate_config(raw, SCHEMA)
    with pytest.raises(Exception, match="backbones.mine.model") as caught:
        build_plan(config)
    # Planned under alley (first in name order), and corridor reads it too.
    assert failed_datasets(caught.value, config, ["corridor"]) == ["corridor"]
    config["datasets"]["corridor"]["methods"].remove("mine")
    with pytest.raises(Exception, match="backbones.mine.model") as caught:
        build_plan(config)
    assert failed_datasets(caught.value, config, ["corridor"]) == []


def test_a_missing_trained_checkpoint_withdraws_the_datasets_that_read_it(tmp_path):
    raw = shipped_config(alley={"methods": ["anyloc_vlad", "nv"], "rerank": {}})
    raw["backbones"]["nv"] = {"backbone": "netvlad", "checkpoint": str(tmp_path / "nv.ckpt")}
    raw["methods"]["nv"] = {"aggregator": "model", "features": "nv"}
    config = validate_config(raw, SCHEMA)
    with pytest.raises(Exception, match="nv.ckpt") as caught:
        build_plan(config)
    assert failed_datasets(caught.value, config, ["alley", "corridor"]) == ["alley"]


def test_a_failed_run_finds_stale_tables_only_among_the_datasets_it_asked_for(tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    run = MethodRun("m", "0123456789abcdef", {}, "anyloc_vlad", reranked=True)
    plan = SimpleNamespace(runs={"a": [run], "b": [run]})
    for name in ("a", "b"):  # the recall store is missing: both tables are stale
        (results / f"recall_{name}.csv").write_text("table")
    root = str(tmp_path) + "/"
    assert stale_reports(plan, root, ["b"]) == [results / "recall_b.csv"]
    assert len(stale_reports(plan, root)) == 2


def test_a_report_that_cannot_list_a_dataset_names_the_data_root_and_the_remedy(tmp_path):
    config = validate_config(shipped_config(), SCHEMA)
    config = copy.deepcopy(config) | {"data_root": str(tmp_path / "data")}
    plan = build_plan(config)
    (gap,) = report_gaps(plan, config, ["corridor"], str(tmp_path) + "/")
    data = tmp_path / "data"
    assert gap == (
        f"dataset 'corridor': its images cannot be read under data_root '{data}' (dataset "
        f"'corridor': folder {data}/corridor does not exist), so no result on disk matches "
        "this config: its tables, curves and figures would be missing"
    )
    message = report_error([gap])
    assert "--config data_root=" in message and gap in message


def test_a_report_before_the_run_names_the_missing_results(tmp_path):
    plan = SimpleNamespace(
        runs={"a": []}, dataset_files={"a": object()}, has_ground_truth={"a": True}
    )
    root = tmp_path / "results"
    root.mkdir()
    (gap,) = report_gaps(plan, {"data_root": "d"}, ["a"], str(tmp_path) + "/")
    assert gap.startswith("dataset 'a' has no results of this config yet: ")
    assert "results/recall_a.csv" in gap and "1 more missing" in gap
    for table in (
        "predictions_a.csv",
        "recall_a.csv",
        "tables/recall_a.html",
        "plots/recall_a.png",
    ):
        (root / table).parent.mkdir(exist_ok=True)
        (root / table).write_text("table")
    assert report_gaps(plan, {"data_root": "d"}, ["a"], str(tmp_path) + "/") == []
