"""The report's tables on disk: which datasets' tables a failure withdraws, clearing the
withdrawn copies a good run supersedes, and a report that would lack items."""

from __future__ import annotations

import copy
from types import SimpleNamespace

import yaml
from synthetic import make_dataset
from workflow_helpers import REPO, toy_config

from vprflow.core.paths import RECALL_CSV, TABLES_MARK
from vprflow.planning.config import validate_config
from vprflow.planning.plan import MethodRun, build_plan
from vprflow.planning.reports import (
    clear_superseded,
    closing_lines,
    mark_stale_tables,
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


def test_a_failed_run_finds_stale_tables_only_among_the_datasets_it_asked_for(tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    run = MethodRun("m", "0123456789abcdef", {}, "anyloc_vlad", reranked=True)
    plan = SimpleNamespace(runs={"a": [run], "b": [run]}, dataset_files={"a": [], "b": []})
    for name in ("a", "b"):  # the recall store is missing: both tables are stale
        (results / f"recall_{name}.csv").write_text("table")
    root = str(tmp_path) + "/"
    assert stale_reports(plan, root, ["b"]) == [results / "recall_b.csv"]
    assert len(stale_reports(plan, root)) == 2


def test_a_dataset_the_plan_cannot_list_has_no_table_told_stale_or_marked_for_rebuilding(
    tmp_path,
):
    """Tables built under another data_root (the README's run with ../shared/data), then
    a plain `snakemake`, whose data_root has no corridor until it is downloaded: planned
    without its images, the dataset's stores have keys no job builds. Their absence
    made its tables "built from other stores than this plan's (...): rebuilt", then
    Snakemake said "Nothing to be done" (it rebuilt nothing)."""
    make_dataset(tmp_path / "data" / "toy", n_places=4)
    config = validate_config(toy_config(tmp_path / "data", methods=["anyloc_vlad"]), SCHEMA)
    root = str(tmp_path) + "/"
    table = tmp_path / RECALL_CSV.format(dataset="toy")
    table.parent.mkdir()
    table.write_text("built from stores this plan does not have")
    mark = tmp_path / TABLES_MARK.format(dataset="toy")
    # Listed, the dataset's recall store is missing: the table is stale, marked to rebuild.
    listed = build_plan(config)
    assert stale_reports(listed, root) == [table]
    assert mark_stale_tables(listed, root, [], ["toy"]) == [table]
    marked = mark.stat().st_mtime
    assert marked > 0
    (tmp_path / "data" / "toy").rename(tmp_path / "elsewhere")
    unlisted = build_plan(config)
    assert stale_reports(unlisted, root) == []
    assert mark_stale_tables(unlisted, root, [], ["toy"]) == []
    assert mark.stat().st_mtime == marked  # neither told stale nor current: kept


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
