"""A dataset's report on disk: the tables and figures it shows, the stores each figure
reads, and withdrawing tables that no longer describe the config."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from vprflow.core.errors import PlanError
from vprflow.core.paths import (
    FIGURE,
    PREDICTIONS_CSV,
    RECALL_CSV,
    RECALL_PLOT,
    RECALL_TABLE,
    store_path,
)
from vprflow.planning.plan import Plan, method_run, method_stores


@dataclass(frozen=True)
class MethodFigure:
    """A figure the report shows for each method that has it (every method has
    ``retrievals``; an aggregator names its ``explanation``). Its rule is made from this
    entry (``workflow/rules/figures.smk``), its caption is
    ``workflow/report/<name>.rst`` and :func:`vprflow.stages.figures.draw_figure` draws
    it with ``draw_<name>``."""

    inputs: tuple[str, ...]  # the method's stores it reads, by name (plan.method_stores)
    heading: str  # the report's subcategory it is filed under
    label: str  # its label in the report


FIGURES = {
    "retrievals": MethodFigure(("dataset", "recall"), "Retrievals", "retrievals"),
    "segment_matches": MethodFigure(
        ("dataset", "recall", "search", "descriptors", "segments"),
        "SegVLAD segment matches",
        "segment matches",
    ),
    "support_maps": MethodFigure(
        ("dataset", "recall", "descriptors", "features"), "SNSM support maps", "support maps"
    ),
}

# The outputs that state results: withdrawn when they may not describe the config.
_SHOWN = (RECALL_CSV, PREDICTIONS_CSV, RECALL_TABLE, RECALL_PLOT)


def dataset_outputs(plan: Plan, dataset: str) -> list[str]:
    """Everything a dataset's report shows: its tables, its recall plot and every
    method's figures."""
    tables = (PREDICTIONS_CSV,)
    if plan.has_ground_truth[dataset]:  # without it there is no recall to show
        tables += (RECALL_CSV, RECALL_TABLE, RECALL_PLOT)
    outputs = [t.format(dataset=dataset) for t in tables]
    for run in plan.runs[dataset]:
        outputs += [
            FIGURE.format(dataset=dataset, figure=figure, method=run.method)
            for figure in run.figures
        ]
    return outputs


def figure_inputs(plan: Plan, dataset: str, method: str, figure: str) -> dict[str, str]:
    """The stores one method's figure reads, by name (see :data:`FIGURES`)."""
    if figure not in method_run(plan, dataset, method).figures:
        raise PlanError(f"no figure {figure!r} of method {method!r} on dataset {dataset!r}")
    stores = method_stores(plan, dataset, method)
    return {name: stores[name] for name in FIGURES[figure].inputs}


def stale_reports(plan: Plan, root: str = "") -> list[Path]:
    """Results tables on disk that do not describe the current config: one of the
    dataset's recall stores is missing or newer than the table. ``root`` is the
    prefix of every path (a host workflow's module ``prefix``)."""
    stale = []
    for dataset, runs in plan.runs.items():
        tables = [Path(root) / t.format(dataset=dataset) for t in _SHOWN]
        for table in tables:
            if not table.exists():
                continue
            built = table.stat().st_mtime
            recalls = [Path(root) / store_path("recall", run.recall_key) for run in runs]
            if any(not r.exists() or r.stat().st_mtime > built for r in recalls):
                stale.append(table)
    return stale


def withdraw_stale_reports(plan: Plan, root: str = "") -> list[Path]:
    """Rename every stale table to ``<name>.stale`` so that a failed run never leaves a
    table that looks current; returns the new paths."""
    return _withdraw(stale_reports(plan, root))


def withdraw_reports(root: str = "", dataset: str = "*") -> list[Path]:
    """Withdraw every table of ``dataset`` (all datasets by default) regardless of age:
    for failures before a plan exists (a config that cannot be planned, a dataset that
    cannot be listed), where none of them describes the current config."""
    return _withdraw([t for p in _SHOWN for t in Path(root or ".").glob(p.format(dataset=dataset))])


def closing_lines(plan: Plan, root: str = "") -> list[str]:
    """What a good run prints last: where each planned dataset's tables are, and the
    command that writes the report."""
    lines = []
    for dataset in plan.runs:
        tables = [t.format(dataset=dataset) for t in (RECALL_CSV, RECALL_TABLE, PREDICTIONS_CSV)]
        present = [t for t in tables if (Path(root) / t).exists()]
        if present:
            lines.append(f"vprflow: {dataset}: {', '.join(present)}")
    if lines:
        lines.append(
            "vprflow: the report with every table and figure: snakemake --report report.html"
            " (with this run's --config and --configfile options)"
        )
    return lines


def clear_superseded(root: str = "") -> list[Path]:
    """Delete every ``<table>.stale`` beside which a fresh ``<table>`` now stands (a good
    run after a failure wrote it again); returns the deleted paths. A withdrawn table
    whose dataset was not rebuilt stays withdrawn."""
    cleared = []
    for pattern in _SHOWN:
        for stale in Path(root or ".").glob(pattern.format(dataset="*") + ".stale"):
            if stale.with_name(stale.name.removesuffix(".stale")).exists():
                stale.unlink()
                cleared.append(stale)
    return cleared


# Snakemake options that run no job: a call with one of them changes no file, so it never
# withdraws a table. Snakemake decides its executor only after the Snakefile is read, so
# at planning time the command line is the only witness.
_NO_JOBS = {
    "-n", "--dry-run", "--dryrun", "--just-print",
    "-S", "--summary", "-D", "--detailed-summary",
    "-l", "--list", "--list-rules", "--lt", "--list-target-rules",
    "--list-changes", "--lc", "--list-code-changes", "--list-input-changes",
    "--list-params-changes", "--list-untracked", "--lu",
    "--lint", "--report", "--report-stylesheet", "--dag", "--rulegraph", "--filegraph",
    "--d3dag", "--containerize", "--print-compilation", "--unlock",
    "--cleanup-metadata", "--cleanup-shadow", "--export-cwl", "--archive",
    "-h", "--help", "--version", "-v",
}  # fmt: skip


def runs_jobs(argv: list[str]) -> bool:
    """Whether a ``snakemake`` command line (``sys.argv``) may run jobs, and so may
    withdraw tables: not with ``-n``, ``--summary``, ``--report``, ``--lint``, ``--dag``
    and the other options that only read. Short flags may be grouped (``-np``)."""
    for arg in argv[1:]:
        if arg == "--":
            break
        name = arg.split("=", 1)[0]
        if name in _NO_JOBS:
            return False
        if name.startswith("-") and not name.startswith("--") and name[1:].isalpha():
            if any(f"-{flag}" in _NO_JOBS for flag in name[1:]):
                return False
    return True


def _withdraw(tables: list[Path]) -> list[Path]:
    moved = []
    for table in tables:
        target = table.with_name(table.name + ".stale")
        table.replace(target)
        moved.append(target)
    return moved
