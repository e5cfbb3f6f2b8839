"""One invocation of Snakemake on the workflow: the validated config, its plan, what the
command asked for, the sample datasets awaiting their download, and every write
planning makes, each a named step of :meth:`Invocation.sync`.

Snakemake includes the Snakefile before it decides what to do with it: while the file is
read it knows whether this process is the main one, but not the targets nor whether the
command runs the workflow (``--summary``, ``--dag``, ``--report`` build a DAG and run no
job; ``--lint`` builds none). It knows both once it builds the DAG, which is when the
rules' input functions run: the first of them tells the invocation (:func:`asked`), and
nothing is written before.
"""

from __future__ import annotations

import atexit
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from vprflow.core.errors import PlanError
from vprflow.core.files import check_writable
from vprflow.core.paths import (
    DOWNLOAD_RECORD,
    FINGERPRINTS,
    OUTPUT_ROOTS,
    PREDICTIONS_CSV,
    RECALL_CSV,
    TABLES_MARK,
    check_inside_outputs,
    dataset_folder,
    store_path,
)
from vprflow.core.runs import collision_message, end_run, other_runs, start_run
from vprflow.data.datasets import DatasetFiles, list_dataset
from vprflow.data.download import awaiting_download, requested_datasets
from vprflow.data.presets import presets, unknown_dataset
from vprflow.planning.checkpoints import by_hand, fetching_checkpoints
from vprflow.planning.config import validate_config
from vprflow.planning.fingerprints import load_fingerprints, save_fingerprints
from vprflow.planning.merges import merge_order
from vprflow.planning.plan import Plan, build_plan, method_stores
from vprflow.planning.published import published_changes, published_plan
from vprflow.planning.reports import (
    clear_superseded,
    closing_lines,
    dataset_outputs,
    figure_inputs,
    mark_stale_tables,
    report_error,
    report_gaps,
    reuse_line,
    tables_mark,
    withdraw_reports,
    withdraw_stale_reports,
)
from vprflow.planning.store_index import write_index

# The options that make a report from the results on disk: the one fact read from the
# command line (see `asked`).
REPORT_OPTIONS = ("--report", "--reporter")


@dataclass(frozen=True)
class Command:
    """What a ``snakemake`` command asked for (:func:`asked`)."""

    targets: tuple[str, ...] = ()
    # It runs the workflow, a dry run included: not a utility that only reads the DAG
    # (--summary, --dag, --list-changes, ...) nor a report made from the results on disk.
    executes: bool = True
    dry_run: bool = False
    # The process that schedules the jobs, not a cluster job's own Snakemake.
    main: bool = True
    # `--report` without `--report-after-run`.
    makes_report: bool = False

    @property
    def runs_jobs(self) -> bool:
        """Only such a process withdraws, clears or marks tables and leaves a run marker."""
        return self.main and self.executes and not self.dry_run

    @property
    def fetches_checkpoints(self) -> bool:
        return fetching_checkpoints(self.targets)


def asked(workflow, argv=()) -> Command:
    """What Snakemake's ``workflow`` object tells of its command once it builds the DAG:
    the targets (``dag_settings``), whether it runs the workflow (only a run is handed an
    executor plugin, a dry run's included), whether dry, whether the main process.

    Whether a command that runs nothing makes a report is told nowhere before the report
    is written (Snakemake hands the report plugin to the report only, after the DAG is
    built, and builds the DAG for --summary, --dag or --report alike), and by then the DAG
    of a report made without the run's data_root has failed on a dataset it cannot list.
    So that one fact is read from ``argv``: a report option given (``REPORT_OPTIONS``).
    """
    executes = workflow.executor_plugin is not None
    given = any(arg.split("=")[0] in REPORT_OPTIONS for arg in argv[1:])
    return Command(
        targets=tuple(sorted(workflow.dag_settings.targets or ())),
        executes=executes,
        dry_run=bool(workflow.dryrun),
        main=bool(workflow.is_main_process),
        makes_report=given and not executes,
    )


def plan_config(config: dict, memo: dict, configfiles=()) -> Plan:
    """``config``'s plan, built while trained checkpoints are missing (its
    ``checkpoint_error`` says which): whether that is an error depends on the command."""
    return build_plan(config, memo, allow_missing_checkpoints=True, configfiles=configfiles)


@dataclass
class Invocation:
    """The plan of a config and what writing it owes the disk. ``root`` is the prefix of
    every path it writes (a host workflow's module ``prefix``)."""

    config: dict
    plan: Plan
    memo: dict  # content hashes (vprflow.planning.fingerprints), memoised between runs
    root: str = ""
    configfiles: tuple = ()
    # Sample datasets whose folder is missing: planned without their images (keys no
    # job builds) until the `download` checkpoint has laid them out (`downloaded`).
    awaiting: set[str] = field(default_factory=set)
    command: Command | None = None  # told by `begin`, once the DAG is built
    # Snakemake's `checkpoints.download.get` of a dataset name (told by `begin`).
    wait: Callable[[str], object] | None = None
    marker: Path | None = None  # this run's marker (vprflow.core.runs)
    others: list[dict] = field(default_factory=list)  # the runs of the folder at its start
    unlistable: set[str] = field(default_factory=set)  # datasets whose listing failed
    tabled: set[str] = field(default_factory=set)  # datasets whose tables the DAG reads
    _saved: int = 0  # memo entries on disk
    _listed: dict[str, DatasetFiles] = field(default_factory=dict)
    _done: set[str] = field(default_factory=set)  # the once-only steps taken
    _indexed: Plan | None = None  # the plan the index on disk maps

    @classmethod
    def read(
        cls, config: dict, schema: str | Path, configfiles=(), overwrite_configfiles=(), root=""
    ) -> Invocation:
        """Validate ``config`` (Snakemake's, read from ``configfiles``) and plan it. It
        writes nothing: a config that fails here withdraws no table (docs/usage.md). Missing
        trained checkpoints are raised once the command is known, unless it fetches them."""
        valid = validate_config(config, schema, merge_order(configfiles, overwrite_configfiles))
        memo = load_fingerprints(root + FINGERPRINTS)
        saved, awaiting = len(memo), set(awaiting_download(valid))
        plan = plan_config(valid, memo, tuple(configfiles))
        return cls(valid, plan, memo, root, tuple(configfiles), awaiting, _saved=saved)

    def replan(self) -> Plan:
        """The config planned again, as a new plan: once a download laid a dataset out, its
        stores get the keys of its images, every other key stays as it was."""
        return plan_config(self.config, self.memo, self.configfiles)

    # ------------------------------------------------------------------ DAG time

    def begin(self, command: Command, wait: Callable[[str], object]) -> None:
        """Told what the command asked for, and how to wait for a dataset's download
        (:meth:`downloaded`): refuse a plan the command cannot use, then write."""
        self.command, self.wait = command, wait
        if self.plan.checkpoint_error and not command.fetches_checkpoints:
            raise PlanError(self.plan.checkpoint_error)
        if command.main and command.fetches_checkpoints:
            for line in by_hand(self.plan.checkpoints):
                print(f"vprflow: {line}", file=sys.stderr)
        if command.main and command.makes_report:
            # A report made without the run's options (its data_root, say) would look for
            # other keys' stores and leave items out without an error.
            asked_for = requested_datasets(self.config, command.targets)
            gaps = report_gaps(self.plan, self.config, asked_for, self.root)
            if gaps:
                raise PlanError(report_error(gaps))
        self.sync()

    def sync(self) -> None:
        """The one place planning writes: what this process owes the disk for its command
        and the current plan. Called once the command is known, after a re-plan, and when
        a dataset's tables are first read or its images cannot be listed; a step made is
        not made again. Only the main process writes (a cluster job reads the Snakefile
        again), and only one that runs jobs (no dry run, no utility, no report) leaves a
        run marker or withdraws tables."""
        command = self.command
        if command is None or not command.main:
            return
        if self._once("writable"):
            self.check_folders()
        if command.runs_jobs and self._once("run"):
            self.mark_run()
            self.forget_stale_downloads()
        self.save_fingerprints()
        if self.plan.checkpoint_error:  # the plan serves only the fetch of checkpoints
            return
        self.write_index()
        self.make_marks()
        if command.executes and self._once("stale"):
            self.mark_stale_tables()
        if command.runs_jobs:
            self.withdraw_unlistable()

    def _once(self, step: str) -> bool:
        first = step not in self._done
        self._done.add(step)
        return first

    # ------------------------------------------------------------------ the writes

    def check_folders(self) -> None:
        """A folder that cannot be written is named before the first write, not by its
        bare OSError."""
        for folder in OUTPUT_ROOTS:
            check_writable(self.root + folder)

    def mark_run(self) -> None:
        """Mark the folder while this run lasts: another run of it at once (--nolock) is
        named now and again if this one fails."""
        self.marker = start_run(self.root, self.command.targets)
        atexit.register(end_run, self.marker)
        self.others = other_runs(self.marker.parent, self.marker)
        if self.others:
            print(f"vprflow: {collision_message(self.others)}", file=sys.stderr)

    def forget_stale_downloads(self) -> None:
        """Remove the record of a download whose folder is gone (or whose data_root moved):
        left in place it would stand for a download that has not happened."""
        for name in sorted(self.awaiting):
            record = Path(self.root + DOWNLOAD_RECORD.format(dataset=name))
            folder = dataset_folder(self.config["data_root"], self.config["datasets"][name])
            if record.exists() and not folder.is_dir():
                record.unlink()
                print(f"vprflow: removed {record}: {folder}, where it records a download, is gone")

    def save_fingerprints(self) -> None:
        if len(self.memo) != self._saved:
            save_fingerprints(self.memo, self.root + FINGERPRINTS)
            self._saved = len(self.memo)

    def write_index(self) -> None:
        """A map of every store to its dataset and methods, and log links by method."""
        if self._indexed is not self.plan:
            write_index(self.plan, self.root)
            self._indexed = self.plan

    def make_marks(self) -> None:
        """The tables mark of each dataset whose tables the DAG reads (:func:`tables_mark`)."""
        for name in sorted(self.tabled):
            tables_mark(self.root, name)

    def mark_stale_tables(self) -> None:
        """A table whose stores this plan no longer has is rebuilt even where Snakemake has
        no record of its job (a copied results/ folder, `.snakemake` removed), which it
        would otherwise keep as current: its dataset's mark is touched."""
        rebuilt = mark_stale_tables(
            self.plan, self.root, self.command.targets, self.config["targets"]
        )
        if rebuilt:
            print(
                f"vprflow: {', '.join(map(str, rebuilt))}: built from other stores than "
                "this plan's (a setting or a stage's format version changed): rebuilt",
                file=sys.stderr,
            )

    def withdraw_unlistable(self) -> None:
        """Withdraw every table of a dataset whose images cannot be listed: none describes
        it any more."""
        for name in sorted(self.unlistable):
            if self._once(f"withdrawn {name}"):
                for table in withdraw_reports(self.root, name):
                    print(f"vprflow: {table} withdrawn: dataset {name!r} cannot be listed")

    # ------------------------------------------------------------------ Snakemake's handlers

    @property
    def runs_jobs(self) -> bool:
        return self.command is not None and self.command.runs_jobs

    def failed(self) -> None:
        """A failed run leaves no table that looks current: the tables of the datasets it
        asked for that are older than their recall stores are renamed to *.stale (other
        datasets' tables are no business of this run)."""
        if not self.runs_jobs:
            return
        # Another run of this folder deletes this one's stores: say so beside the failure.
        others = other_runs(self.marker.parent, self.marker) or self.others
        if others:
            print(f"vprflow: {collision_message(others)}")
        asked_for = requested_datasets(self.config, self.command.targets)
        for table in withdraw_stale_reports(self.plan, self.root, asked_for):
            print(f"vprflow: {table} is out of date after the failure (renamed)")

    def succeeded(self) -> None:
        """A good run supersedes the tables an earlier failure withdrew, and names the
        tables of the datasets it was asked for."""
        if not self.runs_jobs:
            return
        for stale in clear_superseded(self.root):
            print(f"vprflow: removed {stale}: the table beside it is current")
        asked_for = requested_datasets(self.config, self.command.targets)
        print("\n".join(closing_lines(self.plan, self.root, asked_for)))
        started = self.marker.stat().st_mtime if self.marker and self.marker.exists() else 0.0
        if line := reuse_line(self.plan, self.root, started):
            print(line)

    # ------------------------------------------------------------------ datasets

    def dataset_entry(self, name: str) -> dict:
        if name not in self.config["datasets"]:
            raise PlanError(unknown_dataset(name, self.config))
        return self.config["datasets"][name]

    def dataset_files(self, name: str) -> DatasetFiles:
        """Dataset ``name``'s image lists: the plan's, or listed now (once). A dataset that
        cannot be listed is raised while Snakemake builds the DAG, where `onerror` does
        not run: its tables are withdrawn first."""
        if name in self.plan.dataset_files:
            return self.plan.dataset_files[name]
        if name not in self._listed:
            try:
                files = list_dataset(self.config["data_root"], name, self.dataset_entry(name))
            except Exception:
                self.unlistable.add(name)
                self.sync()
                raise
            self._listed[name] = files
        return self._listed[name]

    def downloaded(self, name: str) -> Plan:
        """The plan, once dataset ``name``'s stores may be read. A sample dataset awaiting
        its download waits for it (Snakemake's `download` checkpoint raises until it ran,
        in a dry run for good, and calls again), then the config is planned again with its
        images. A name that is no dataset of the config (a mistyped target) is named here,
        with the datasets there are."""
        entry = self.dataset_entry(name)
        if name not in self.awaiting:
            return self.plan
        self.wait(name)
        folder = dataset_folder(self.config["data_root"], entry)
        if not folder.is_dir():
            record = self.root + DOWNLOAD_RECORD.format(dataset=name)
            raise PlanError(
                f"dataset {name!r}: folder {folder} does not exist, though {record} records "
                "a download there; a run without -n (--dry-run) fetches it again"
            )
        self.awaiting.discard(name)
        self.plan = self.replan()
        self._listed.clear()
        self.sync()
        return self.plan

    # ------------------------------------------------------------------ the rules' inputs

    def default_targets(self) -> list[str]:
        """What `snakemake` without a target builds: every output of the `targets` datasets
        (names are plain, by the schema: checked all the same)."""
        paths = [p for name in self.config["targets"] for p in dataset_outputs(self.plan, name)]
        for path in paths:
            check_inside_outputs(path)
        return paths

    def prediction_inputs(self, name: str) -> dict:
        """A dataset's tables read its truth store, every method's recall store and its
        tables mark (:func:`tables_mark`)."""
        plan = self.downloaded(name)
        if name not in self.tabled:
            self.tabled.add(name)
            self.sync()
        return {
            "dataset": store_path("dataset", plan.dataset_keys[name]),
            "recalls": [store_path("recall", run.recall_key) for run in plan.runs[name]],
            "mark": TABLES_MARK.format(dataset=name),
        }

    def table_inputs(self, name: str) -> dict:
        """A recall table's inputs, its per-query predictions among them (a table whose
        rankings are missing could not be checked query by query); a dataset without
        ground truth has no table, and asking for one says so."""
        if self.dataset_entry(name)["ground_truth"]["kind"] == "none":
            raise PlanError(
                f"dataset {name!r} has ground_truth kind 'none': there is no recall to "
                f"tabulate. Its rankings are in {PREDICTIONS_CSV.format(dataset=name)} "
                "(`snakemake` builds them and its figures when the dataset is in `targets`)"
            )
        return {**self.prediction_inputs(name), "predictions": PREDICTIONS_CSV.format(dataset=name)}

    def table_rows(self, name: str) -> list[dict]:
        return [{"method": r.method, "params": r.row_params} for r in self.plan.runs[name]]

    def method_stores(self, dataset: str, method: str, names) -> dict[str, str]:
        """Those of ``names`` that one method's row has of its stores."""
        stores = method_stores(self.downloaded(dataset), dataset, method)
        return {name: stores[name] for name in names if name in stores}

    def figure_stores(self, dataset: str, method: str, figure: str) -> dict[str, str]:
        return figure_inputs(self.downloaded(dataset), dataset, method, figure)

    def published_table(self, name: str) -> str:
        """The recall table beside which a preset's published rows go; a dataset that is
        no preset fails here, before its table is built."""
        if name not in presets():
            raise PlanError(
                f"results/published_{name}.csv: dataset {name!r} is not a vprflow preset, "
                "so it has no published rows (docs/datasets.md lists the presets)"
            )
        return RECALL_CSV.format(dataset=name)

    def published_differences(
        self, name: str, raw: dict, shipped: str | Path, schema: str | Path
    ) -> dict[str, str]:
        """By method, how this run makes preset ``name``'s published rows otherwise than
        the published setting (the preset with the ``shipped`` config file; ``raw``:
        Snakemake's config, before validation)."""
        if name not in presets() or name not in self.plan.runs:
            return {}
        methods = [entry["row"] for entry in presets()[name].published if entry.get("row")]
        try:
            reference = published_plan(raw, shipped, name, schema, self.memo)
        except Exception as error:  # named in the table, beside each row
            reference = error
        return published_changes(self.plan, reference, name, methods)
