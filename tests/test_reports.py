"""The report's tables on disk: which command lines may withdraw them, and clearing the
withdrawn copies a good run supersedes."""

from __future__ import annotations

import pytest

from vprflow.planning.reports import clear_superseded, closing_lines, runs_jobs


@pytest.mark.parametrize(
    "argv",
    [
        ["snakemake", "-n", "--cores", "2"],
        ["snakemake", "--cores", "2", "--dry-run", "results/recall_corridor.csv"],
        ["snakemake", "-np"],
        ["snakemake", "-pn", "--cores=2"],
        ["snakemake", "--summary"],
        ["snakemake", "--report", "report.html"],
        ["snakemake", "--report=report.html"],
        ["snakemake", "--lint"],
        ["snakemake", "--dag"],
        ["snakemake", "--list-rules"],
        ["snakemake", "--unlock"],
    ],
)
def test_a_command_that_runs_no_job_withdraws_nothing(argv):
    assert not runs_jobs(argv)


@pytest.mark.parametrize(
    "argv",
    [
        ["snakemake", "--cores", "2"],
        ["snakemake", "-c2", "results/recall_corridor.csv"],
        ["snakemake", "-p", "--cores", "2", "--config", "data_root=../shared/data"],
        ["snakemake", "--cores", "2", "--", "results/n.csv"],
    ],
)
def test_a_command_that_runs_jobs_may_withdraw(argv):
    assert runs_jobs(argv)


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
    from types import SimpleNamespace

    results = tmp_path / "results"
    results.mkdir()
    (results / "recall_a.csv").write_text("table")
    (results / "predictions_a.csv").write_text("table")
    plan = SimpleNamespace(runs={"a": [], "b": []})  # b has no table on disk
    lines = closing_lines(plan, str(tmp_path) + "/")
    assert lines[0] == "vprflow: a: results/recall_a.csv, results/predictions_a.csv"
    assert "snakemake --report report.html" in lines[1] and len(lines) == 2
