"""One invocation of the workflow without Snakemake (vprflow.planning.invocation): what a
command asked for, read from Snakemake's workflow object; what planning writes, and only
once the command is known and only where the command may write."""

from __future__ import annotations

import copy
import json
import os
from types import SimpleNamespace

import pytest
from synthetic import make_dataset
from workflow_helpers import SCHEMA, toy_config

from vprflow.core.errors import PlanError
from vprflow.core.paths import DOWNLOAD_RECORD, INDEX, PREDICTIONS_CSV, RECALL_CSV, TABLES_MARK
from vprflow.core.runs import RUNS, end_run
from vprflow.planning.invocation import Command, Invocation, asked

RUN = Command(targets=("results/recall_toy.csv",))
DRY_RUN = Command(dry_run=True)
SUMMARY = Command(executes=False)  # --summary, --dag, --list-changes ...
CLUSTER_JOB = Command(main=False)
DOWNLOAD = {"url": "file:///toy.zip", "strip": 1, "layout": {"images/db": "ref"}}


def workflow(executes=True, dry_run=False, main=True, targets=()):
    """What Snakemake's workflow object shows an input function of its DAG."""
    return SimpleNamespace(
        executor_plugin=object() if executes else None,
        dryrun=dry_run,
        is_main_process=main,
        dag_settings=SimpleNamespace(targets=frozenset(targets)),
    )


def no_download(name):
    raise AssertionError(f"dataset {name!r} waited for a download")


@pytest.fixture
def toy(tmp_path):
    """A finished-looking toy dataset's config; the invocation's root is ``tmp_path``."""
    make_dataset(tmp_path / "data" / "toy", n_places=4)
    return toy_config(tmp_path / "data", methods=["anyloc_vlad"])


def read(config, tmp_path) -> Invocation:
    return Invocation.read(copy.deepcopy(config), SCHEMA, root=f"{tmp_path}/")


def written(tmp_path) -> list[str]:
    """Every file under results/, logs/ and .snakemake/ of ``tmp_path``."""
    return sorted(
        str(p.relative_to(tmp_path))
        for root in ("results", "logs", ".snakemake")
        for p in (tmp_path / root).rglob("*")
        if p.is_file()
    )


# ------------------------------------------------------------------ what the command asked


def test_a_command_runs_the_workflow_only_where_snakemake_hands_it_an_executor():
    run = asked(workflow())
    assert run.executes and run.runs_jobs
    dry = asked(workflow(dry_run=True))
    assert dry.executes and dry.dry_run and not dry.runs_jobs
    summary = asked(workflow(executes=False), ["snakemake", "--summary"])
    assert not summary.executes and not summary.runs_jobs and not summary.makes_report
    assert not asked(workflow(main=False)).runs_jobs


def test_the_targets_are_those_snakemake_builds_the_dag_for():
    targets = {"results/recall_b.csv", "results/recall_a.csv"}
    assert asked(workflow(targets=targets)).targets == tuple(sorted(targets))
    assert asked(workflow()).targets == ()
    assert asked(workflow(targets={"trained_checkpoints"})).fetches_checkpoints


@pytest.mark.parametrize(
    ("argv", "executes", "expected"),
    [
        (["snakemake", "--report", "report.html"], False, True),
        (["snakemake", "--report=r.html", "--config", "data_root=d"], False, True),
        (["snakemake", "--reporter", "html"], False, True),
        (["snakemake", "--report", "r.html", "--report-after-run", "-c2"], True, False),
        (["snakemake", "--summary"], False, False),
        (["snakemake", "-c2", "results/report.csv"], True, False),
    ],
)
def test_only_a_report_option_of_a_command_that_runs_nothing_makes_a_report_from_disk(
    argv, executes, expected
):
    assert asked(workflow(executes=executes), argv).makes_report is expected


# ------------------------------------------------------------------ what is written, where


def test_reading_and_planning_the_config_writes_nothing(toy, tmp_path):
    invocation = read(toy, tmp_path)
    assert invocation.plan.runs["toy"] and invocation.memo  # the images were hashed
    assert written(tmp_path) == []


def test_a_run_writes_the_memo_the_index_and_the_marks_and_marks_the_folder_while_it_lasts(
    toy, tmp_path
):
    invocation = read(toy, tmp_path)
    invocation.begin(RUN, no_download)
    assert json.loads((tmp_path / RUNS / invocation.marker.name).read_text())["targets"] == [
        "results/recall_toy.csv"
    ]
    assert (tmp_path / INDEX).read_text().count("\tanyloc_vlad\t") > 0
    assert (tmp_path / TABLES_MARK.format(dataset="toy")).stat().st_mtime == 0
    assert (tmp_path / "results" / "cache" / "fingerprints.json").exists()
    end_run(invocation.marker)
    assert not list((tmp_path / RUNS).iterdir())


@pytest.mark.parametrize("command", [DRY_RUN, SUMMARY])
def test_a_dry_run_or_a_utility_writes_the_index_but_leaves_no_run_marker(command, toy, tmp_path):
    read(toy, tmp_path).begin(command, no_download)
    assert (tmp_path / INDEX).exists() and not (tmp_path / RUNS).exists()


def test_a_cluster_jobs_own_snakemake_writes_nothing(toy, tmp_path):
    read(toy, tmp_path).begin(CLUSTER_JOB, no_download)
    assert written(tmp_path) == []


def test_missing_checkpoints_stop_every_command_but_their_fetch_before_anything_is_written(
    toy, tmp_path
):
    toy["backbones"]["nv"] = {"backbone": "netvlad", "checkpoint": str(tmp_path / "nv.ckpt")}
    toy["methods"]["nv"] = {"aggregator": "model", "features": "nv"}
    toy["datasets"]["toy"]["methods"] = ["anyloc_vlad", "nv"]
    invocation = read(toy, tmp_path)  # planned all the same, to fetch them
    with pytest.raises(PlanError, match="nv.ckpt"):
        invocation.begin(RUN, no_download)
    assert written(tmp_path) == []
    read(toy, tmp_path).begin(Command(targets=("trained_checkpoints",), dry_run=True), None)
    assert not (tmp_path / INDEX).exists()


def test_a_stale_table_touches_its_mark_once_the_command_is_known_and_no_stale_one_resets_it(
    toy, tmp_path
):
    table = tmp_path / RECALL_CSV.format(dataset="toy")
    table.parent.mkdir(parents=True)
    table.write_text("built from stores this plan does not have")
    mark = tmp_path / TABLES_MARK.format(dataset="toy")
    invocation = read(toy, tmp_path)
    assert not mark.exists()
    invocation.begin(DRY_RUN, no_download)  # a dry run shows what a run does
    assert mark.stat().st_mtime > 0
    table.unlink()
    read(toy, tmp_path).begin(DRY_RUN, no_download)
    assert mark.stat().st_mtime == 0


# ------------------------------------------------------------------ datasets at DAG time


def test_a_dataset_that_cannot_be_listed_withdraws_its_tables_in_a_run_only(toy, tmp_path):
    tables = [tmp_path / t.format(dataset="toy") for t in (RECALL_CSV, PREDICTIONS_CSV)]
    tables[0].parent.mkdir(parents=True)
    for table in tables:
        table.write_text("a table")
    (tmp_path / "data" / "toy").rename(tmp_path / "elsewhere")
    dry = read(toy, tmp_path)
    dry.begin(DRY_RUN, no_download)
    with pytest.raises(Exception, match="does not exist"):
        dry.dataset_files("toy")
    assert all(t.exists() for t in tables)
    run = read(toy, tmp_path)
    run.begin(RUN, no_download)
    with pytest.raises(Exception, match="does not exist"):
        run.dataset_files("toy")
    assert not any(t.exists() for t in tables)
    assert all(t.with_name(t.name + ".stale").exists() for t in tables)
    end_run(run.marker)


def test_a_report_without_the_runs_data_root_fails_naming_the_dataset(toy, tmp_path):
    (tmp_path / "data" / "toy").rename(tmp_path / "elsewhere")
    with pytest.raises(PlanError, match="dataset 'toy': its images cannot be read"):
        read(toy, tmp_path).begin(Command(executes=False, makes_report=True), no_download)


def test_an_unknown_dataset_is_named_with_the_configured_ones(toy, tmp_path):
    invocation = read(toy, tmp_path)
    invocation.begin(DRY_RUN, no_download)
    with pytest.raises(PlanError, match=r"toyy.*toy"):
        invocation.downloaded("toyy")


def test_a_download_gives_a_new_plan_with_the_datasets_images_and_leaves_the_old_one(toy, tmp_path):
    (tmp_path / "data" / "toy").rename(tmp_path / "fetched")
    toy["datasets"]["toy"]["download"] = DOWNLOAD
    invocation = read(toy, tmp_path)
    assert invocation.awaiting == {"toy"}
    before = invocation.plan
    invocation.begin(RUN, no_download)
    index_before = (tmp_path / INDEX).read_text()

    def download(name):  # what the `download` checkpoint's job leaves
        (tmp_path / "fetched").rename(tmp_path / "data" / name)

    invocation.wait = download
    after = invocation.downloaded("toy")
    assert after is invocation.plan and after is not before
    assert "toy" in after.dataset_files and "toy" not in before.dataset_files
    assert after.images_keys["toy"] != before.images_keys["toy"]
    assert after.images_keys["toy"] in (tmp_path / INDEX).read_text()
    assert (tmp_path / INDEX).read_text() != index_before
    assert invocation.awaiting == set() and invocation.downloaded("toy") is after
    end_run(invocation.marker)


def test_a_dry_run_shows_the_download_and_plans_the_dataset_without_its_images(toy, tmp_path):
    toy["datasets"]["toy"]["download"] = DOWNLOAD
    toy["data_root"] = str(tmp_path / "nowhere")
    invocation = read(toy, tmp_path)
    before = invocation.plan

    class Incomplete(Exception):  # Snakemake's IncompleteCheckpointException
        pass

    def scheduled(name):
        raise Incomplete(name)

    invocation.begin(DRY_RUN, scheduled)
    with pytest.raises(Incomplete):
        invocation.downloaded("toy")
    assert invocation.plan is before and invocation.awaiting == {"toy"}


@pytest.mark.parametrize(("command", "kept"), [(RUN, False), (DRY_RUN, True)])
def test_a_run_removes_the_record_of_a_download_whose_folder_is_gone(command, kept, toy, tmp_path):
    toy["datasets"]["toy"]["download"] = DOWNLOAD
    toy["data_root"] = str(tmp_path / "nowhere")
    record = tmp_path / DOWNLOAD_RECORD.format(dataset="toy")
    record.parent.mkdir(parents=True)
    record.write_text("{}")
    invocation = read(toy, tmp_path)
    invocation.begin(command, no_download)
    assert record.exists() is kept
    if invocation.marker:
        end_run(invocation.marker)


# ------------------------------------------------------------------ Snakemake's handlers


def test_a_failed_run_withdraws_the_stale_tables_it_asked_for_and_a_dry_run_none(
    toy, tmp_path, capsys
):
    table = tmp_path / RECALL_CSV.format(dataset="toy")
    table.parent.mkdir(parents=True)
    table.write_text("older than its recall stores, which are missing")
    dry = read(toy, tmp_path)
    dry.begin(DRY_RUN, no_download)
    dry.failed()
    assert table.exists()
    run = read(toy, tmp_path)
    run.begin(Command(), no_download)
    run.failed()
    assert not table.exists() and table.with_name(table.name + ".stale").exists()
    assert "is out of date after the failure" in capsys.readouterr().out
    end_run(run.marker)


def test_a_good_run_names_the_tables_of_the_datasets_it_asked_for(toy, tmp_path, capsys):
    table = tmp_path / RECALL_CSV.format(dataset="toy")
    table.parent.mkdir(parents=True)
    table.write_text("a table")
    os.utime(table, (0, 0))
    run = read(toy, tmp_path)
    run.begin(Command(), no_download)
    run.succeeded()
    assert f"vprflow: toy: {RECALL_CSV.format(dataset='toy')}" in capsys.readouterr().out
    end_run(run.marker)
