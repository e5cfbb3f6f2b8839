"""A dataset's report on disk: the tables and figures it shows, the stores each figure
reads, and withdrawing tables that no longer describe the config."""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

from vprflow.core.errors import PlanError
from vprflow.core.paths import (
    FIGURE,
    PREDICTIONS_CSV,
    RECALL_CSV,
    RECALL_PLOT,
    RECALL_TABLE,
    TABLES_MARK,
    log_pattern,
    store_path,
)
from vprflow.core.reuse import IMAGES_PATTERN, STAGES
from vprflow.data.datasets import list_dataset
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


def stale_reports(plan: Plan, root: str = "", datasets: list[str] | None = None) -> list[Path]:
    """Results tables on disk that do not describe the current config: one of the
    dataset's recall stores is missing or newer than the table. ``root`` is the
    prefix of every path (a host workflow's module ``prefix``); ``datasets`` limits the
    search to those datasets (all planned ones by default). Only the tables of the
    datasets the plan listed (:func:`judged_datasets`) are judged."""
    stale = []
    for dataset in judged_datasets(plan, datasets):
        tables = [Path(root) / t.format(dataset=dataset) for t in _SHOWN]
        recalls = [Path(root) / store_path("recall", run.recall_key) for run in plan.runs[dataset]]
        for table in tables:
            if not table.exists():
                continue
            built = table.stat().st_mtime
            if any(not r.exists() or r.stat().st_mtime > built for r in recalls):
                stale.append(table)
    return stale


def judged_datasets(plan: Plan, datasets: list[str] | None = None) -> list[str]:
    """Of ``datasets`` (every planned one by default), those whose tables the plan can
    tell stale: the ones it listed. A dataset it could not list (a sample awaiting its
    download, a folder missing under ``data_root``) is planned without its images, so
    its stores' keys are of no images and their absence says nothing of its tables:
    built elsewhere from the same images (another ``data_root``) they may be current."""
    return [
        name
        for name in plan.runs
        if name in plan.dataset_files and (datasets is None or name in datasets)
    ]


def tables_mark(root: str, dataset: str) -> str:
    """The mark a dataset's tables read (:func:`mark_stale_tables`), made under ``root``
    on first use with the oldest modification time, so that it reruns nothing until
    touched; its path as rules name it (a module's ``prefix`` is added by Snakemake)."""
    path = TABLES_MARK.format(dataset=dataset)
    mark = Path(root) / path
    if not mark.exists():
        mark.parent.mkdir(parents=True, exist_ok=True)
        mark.touch()
        os.utime(mark, (0, 0))
    return path


def mark_stale_tables(plan: Plan, root: str, targets, default_datasets: list[str]) -> list[Path]:
    """Set each dataset's tables mark (:func:`tables_mark`): to now where one of its
    tables the command builds is stale (:func:`stale_reports`), to the oldest time
    where none of its tables is; returns the stale tables. The tables a command builds:
    those its ``targets`` name, or, with no target or ``all``, those of
    ``default_datasets`` (the config's ``targets``).

    Snakemake keeps an existing table whose input stores are missing unless its record
    of the job says they changed, and a copied results/ folder, or one whose
    ``.snakemake`` is gone, has none: a table built from an older config's stores, or
    an older format version's, would stand as current. The mark is an input of the
    tables' rules: newer than a table, it reruns them on the current plan's stores. A
    dry run sets it too, so that it shows what a run does; a config changed back before
    the run sets it back, and nothing reruns."""
    wanted = {os.path.normpath(t) for t in targets}
    if not targets or "all" in targets:
        wanted |= {
            os.path.normpath(Path(root) / path)
            for name in default_datasets
            for path in dataset_outputs(plan, name)
        }
    rebuilt = []
    # A dataset the plan could not list keeps its mark: nothing here tells its tables
    # stale or current.
    for dataset in judged_datasets(plan):
        stale = stale_reports(plan, root, [dataset])
        asked = [t for t in stale if os.path.normpath(t) in wanted]
        if asked or not stale:
            mark = Path(root) / tables_mark(root, dataset)
            os.utime(mark, None if asked else (0, 0))
        rebuilt += asked
    return rebuilt


def withdraw_stale_reports(
    plan: Plan, root: str = "", datasets: list[str] | None = None
) -> list[Path]:
    """Rename every stale table (of ``datasets``: those a failed run asked for) to
    ``<name>.stale`` so that a failed run never leaves a table that looks current;
    returns the new paths."""
    return _withdraw(stale_reports(plan, root, datasets))


def withdraw_reports(root: str = "", dataset: str = "*") -> list[Path]:
    """Withdraw every table of ``dataset`` (all datasets by default) regardless of age:
    for a dataset whose images cannot be listed while the jobs are planned, which none of
    its tables describes any more. A config that fails to plan withdraws none: no job
    ran, and each table still describes the stores it was built from."""
    return _withdraw([t for p in _SHOWN for t in Path(root or ".").glob(p.format(dataset=dataset))])


def closing_lines(plan: Plan, root: str = "", datasets: list[str] | None = None) -> list[str]:
    """What a good run prints last: where the tables of ``datasets`` (those the run asked
    for; every planned one by default) are, and the command that writes the report."""
    lines = []
    for dataset in plan.runs if datasets is None else datasets:
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


def reuse_line(plan: Plan, root: str = "", since: float = 0.0) -> str | None:
    """The closing line on the per-image stages (:data:`vprflow.core.reuse.STAGES`): how
    many images this run's jobs computed and how many they took from stores already
    there, summed from the logs of the plan's stores written since ``since`` (the run's
    start); None where no such job ran."""
    computed = reused = jobs = 0
    for stage in STAGES:
        for key in plan.stages.get(stage, {}):
            folder = Path(root) / Path(log_pattern(stage).format(key=key)).parent
            for log in folder.glob("*.log") if folder.is_dir() else ():
                if log.stat().st_mtime < since:
                    continue
                match = re.search(IMAGES_PATTERN, log.read_text(errors="replace"))
                if match:
                    jobs += 1
                    computed += int(match[1])
                    reused += int(match[2])
    if not jobs:
        return None
    return (
        f"vprflow: features and segments: {computed} images computed, {reused} reused from "
        f"stores already there ({jobs} jobs)"
    )


def report_gaps(plan: Plan, config: dict, datasets: list[str], root: str = "") -> list[str]:
    """Why ``snakemake --report`` would leave out items of ``datasets`` (those it shows):
    one line per dataset whose images cannot be listed under ``data_root`` (every key
    then differs from the run's, so none of its results is found), or whose tables,
    figures or recall stores of this config are not on disk."""

    gaps = []
    for name in datasets:
        if name not in plan.dataset_files:
            try:
                list_dataset(config["data_root"], name, config["datasets"][name])
                reason = "it cannot be listed"
            except Exception as error:
                # The first sentence says what is wrong; the rest is how to get the data,
                # which a report after a good run does not need.
                reason = str(error).split(". ", 1)[0]
            gaps.append(
                f"dataset {name!r}: its images cannot be read under data_root "
                f"{config['data_root']!r} ({reason}), so no result on disk matches this "
                "config: its tables, curves and figures would be missing"
            )
            continue
        missing = [o for o in dataset_outputs(plan, name) if not (Path(root) / o).exists()]
        missing += [
            f"the recall store of {run.method} ({store_path('recall', run.recall_key)})"
            for run in plan.runs[name]
            if not (Path(root) / store_path("recall", run.recall_key)).exists()
        ]
        if missing:
            shown = ", ".join(missing[:3]) + (
                f" and {len(missing) - 3} more" if len(missing) > 3 else ""
            )
            gaps.append(f"dataset {name!r} has no results of this config yet: {shown} missing")
    return gaps


def report_error(gaps: list[str]) -> str:
    """The message a report that would lack items fails with: each gap and the remedy."""
    lines = "\n".join(f"  - {gap}" for gap in gaps)
    return (
        f"The report would lack items:\n{lines}\n"
        "Give the report the options of the run that built the results (its --config "
        "data_root=... and --configfile), e.g. snakemake --report report.html --config "
        "data_root=../shared/data after a run with that data_root; or run snakemake with "
        "these options first."
    )


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


def _withdraw(tables: list[Path]) -> list[Path]:
    moved = []
    for table in tables:
        target = table.with_name(table.name + ".stale")
        table.replace(target)
        moved.append(target)
    return moved
