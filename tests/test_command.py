"""What a ``snakemake`` command asks for, read with Snakemake's own parser while the
workflow is read (vprflow.planning.command)."""

from __future__ import annotations

import pytest

from vprflow.planning.command import NOT_RUNNING, Command, read_command


@pytest.mark.parametrize(
    "argv",
    [
        ["snakemake", "--summary"],
        ["snakemake", "-S"],
        ["snakemake", "--report", "report.html"],
        ["snakemake", "--report=report.html"],
        ["snakemake", "--lint"],
        ["snakemake", "--dag"],
        ["snakemake", "--list-rules"],
        ["snakemake", "--unlock"],
        ["snakemake", "--cores", "1", "--delete-all-output"],
    ],
)
def test_a_command_that_does_not_run_the_workflow_reads_so(argv):
    assert not read_command(argv).runs_workflow


@pytest.mark.parametrize(
    "argv",
    [
        ["snakemake", "--cores", "2"],
        ["snakemake", "-np"],  # a dry run runs the workflow: Snakemake says it is dry
        ["snakemake", "-c2", "results/recall_corridor.csv"],
        ["snakemake", "-p", "--cores", "2", "--config", "data_root=../shared/data"],
        ["snakemake", "--report", "r.html", "--report-after-run", "--cores", "2"],
    ],
)
def test_a_command_that_runs_the_workflow_reads_so(argv):
    assert read_command(argv).runs_workflow


def test_the_targets_are_snakemakes_whatever_the_options_around_them():
    argv = ["snakemake", "-c2", "--config", "x_y=1", "--", "results/a.csv", "results/b.csv"]
    assert set(read_command(argv).targets) == {"results/a.csv", "results/b.csv"}
    assert read_command(["snakemake", "-np", "trained_checkpoints"]).targets == (
        "trained_checkpoints",
    )


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (["snakemake", "--report", "report.html"], True),
        (["snakemake", "--report=r.html", "--config", "data_root=d"], True),
        (["snakemake", "--report", "r.html", "--report-after-run", "--cores", "2"], False),
        (["snakemake", "--cores", "2"], False),
    ],
)
def test_only_a_report_from_the_results_on_disk_makes_a_report_before_running(argv, expected):
    assert read_command(argv).makes_report is expected


def test_a_process_that_is_no_snakemake_command_line_reads_as_a_plain_run():
    assert read_command(["my-driver", "--not-a-snakemake-option"]) == Command()


def test_every_utility_named_is_an_option_of_this_snakemake():
    from snakemake.cli import get_argument_parser

    dests = {action.dest for action in get_argument_parser()._actions}
    assert set(NOT_RUNNING) <= dests
