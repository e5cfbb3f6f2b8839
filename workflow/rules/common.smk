# Config validation, the content-addressed plan, and the input functions every rule uses.
import atexit
import sys
from functools import cache
from pathlib import Path

from vprflow.planning.checkpoints import fetching_checkpoints
from vprflow.planning.command import read_command
from vprflow.planning.config import validate_config
from vprflow.planning.merges import merge_order
from vprflow.core.errors import PlanError
from vprflow.core.files import check_writable
from vprflow.core.runs import collision_message, end_run, other_runs, start_run
from vprflow.data.datasets import list_dataset
from vprflow.data.download import awaiting_download, requested_datasets
from vprflow.planning.fingerprints import load_fingerprints, save_fingerprints
from vprflow.core.paths import (
    DOWNLOAD_RECORD,
    EXPORT,
    FIGURE,
    FINGERPRINTS,
    KAPTURE_PAIRS,
    PAIRS,
    PREDICTIONS_CSV,
    PUBLISHED_CSV,
    RECALL_CSV,
    RECALL_PLOT,
    NAME_PATTERN,
    OUTPUT_ROOTS,
    RECALL_TABLE,
    benchmark_pattern,
    check_inside_outputs,
    dataset_folder,
    log_pattern,
    shard_pattern,
    store_path,
    store_pattern,
)
from vprflow.planning.plan import SHARDED, build_plan, method_stores
from vprflow.planning.published import published_changes, published_plan
from vprflow.data.presets import presets, unknown_dataset
from vprflow.planning.reports import (
    FIGURES,
    clear_superseded,
    closing_lines,
    dataset_outputs,
    figure_inputs,
    mark_stale_tables,
    tables_mark,
    withdraw_reports,
    withdraw_stale_reports,
)
from vprflow.stages.jobs import built_shard_ranges, shard_ranges
from vprflow.planning.store_index import write_index


configfile: "config/config.yaml"


# Found next to this file (not via workflow.basedir), so that a host workflow that
# imports vprflow as a module validates against vprflow's schema.
SCHEMA = Path(workflow.current_basedir).parent / "schemas" / "config.schema.yaml"
# The config shipped beside the workflow: a preset's published setting is made with its
# components (results/published_<preset>.csv names what a run does otherwise).
SHIPPED_CONFIG = Path(workflow.current_basedir).parents[1] / "config" / "config.yaml"
# A host workflow that imports vprflow as a module with a `prefix` finds every output
# under it; the few paths this file opens itself (not via rules) follow.
_modifier = getattr(workflow.modifier, "path_modifier", None)
PREFIX = getattr(_modifier, "prefix", None) or ""
# The targets and whether the command runs the workflow, as Snakemake's parser reads them:
# Snakemake decides both only after it has read this file.
COMMAND = read_command(sys.argv)
# Planning writes under results/ and logs/ from here on, a dry run too: a folder that
# cannot be written is named now, not by the first write's bare OSError.
for _root in OUTPUT_ROOTS:
    check_writable(PREFIX + _root)
# Only the process that may run jobs withdraws or clears tables: never a dry run (Snakemake
# knows it already), a summary, a lint, a report or a cluster job.
RUNS_JOBS = (
    workflow.is_main_process
    and not workflow.output_settings.dryrun
    and COMMAND.runs_workflow
)
# A run that runs jobs marks the folder while it lasts: another run of it at once
# (--nolock) is named now and again if this one fails.
if RUNS_JOBS:
    RUN_MARKER = start_run(PREFIX, COMMAND.targets)
    atexit.register(end_run, RUN_MARKER)
    OTHER_RUNS = other_runs(RUN_MARKER.parent, RUN_MARKER)
    if OTHER_RUNS:
        print(f"vprflow: {collision_message(OTHER_RUNS)}", file=sys.stderr)
# A failure from here to the plan (a config that does not validate or cannot be planned, a
# trained checkpoint not yet fetched) withdraws no table: no job ran, and each finished
# table still describes the stores it was built from (docs/usage.md).
CONFIG = validate_config(
    config,
    SCHEMA,
    merge_order(workflow.configfiles, workflow.overwrite_configfiles),
)
# Content hashes of images, local model weights and imported files, memoised
# between runs.
_memo = load_fingerprints(PREFIX + FINGERPRINTS)
_memo_size = len(_memo)
# Sample datasets whose folder is missing: planned without their images (keys no
# job builds) until the `download` checkpoint has laid them out (`downloaded`).
AWAITING_DOWNLOAD = set(awaiting_download(CONFIG))
# Missing checkpoints are one error naming them all, unless this run fetches them.
_allow_missing = fetching_checkpoints(COMMAND.targets)
PLAN = build_plan(
    CONFIG,
    _memo,
    allow_missing_checkpoints=_allow_missing,
    configfiles=workflow.configfiles,
)
if len(_memo) != _memo_size:
    save_fingerprints(_memo, PREFIX + FINGERPRINTS)
# A map of every store to its dataset and methods, and log links by method. Written
# here, not in `onstart` (which a host workflow's module import never runs); not by
# cluster job steps, which parse this file again.
if workflow.is_main_process and not PLAN.checkpoint_error:
    write_index(PLAN, PREFIX)
# A table whose stores this plan no longer has is rebuilt even where Snakemake has no
# record of its job (a copied results/ folder, `.snakemake` removed), which it would
# otherwise keep as current: its dataset's mark, an input of the tables, is touched.
if workflow.is_main_process and not PLAN.checkpoint_error and COMMAND.runs_workflow:
    _rebuilt = mark_stale_tables(PLAN, PREFIX, COMMAND.targets, CONFIG["targets"])
    if _rebuilt:
        print(
            f"vprflow: {', '.join(map(str, _rebuilt))}: built from other stores than "
            "this plan's (a setting or a stage's format version changed): rebuilt",
            file=sys.stderr,
        )
# The stages vprflow.planning.plan.STAGES runs in shards: the `gather` rule combines them.
SHARDED_STAGES = "|".join(SHARDED)


wildcard_constraints:
    key="[0-9a-f]{16}",
    dataset=NAME_PATTERN,
    method=NAME_PATTERN,
    start=r"\d+",
    stop=r"\d+",


def planned(stage, wildcards):
    return PLAN.get(stage, wildcards.key)


def stage_inputs(stage):
    """Input function: the upstream stores of a stage instance, by name."""
    return lambda wildcards: planned(stage, wildcards).input_paths()


def stage_record(stage):
    """Params function: the stage's hashed record (what its key is made of)."""
    return lambda wildcards: planned(stage, wildcards).record


def stage_run_params(stage):
    """Params function: how a stage instance runs (device, batch size), which shapes none
    of its output. It takes `output` so that Snakemake's params trigger leaves it out:
    the store's key already holds every setting that shapes the result, and a device or
    batch-size change must rerun nothing."""
    return lambda wildcards, output: planned(stage, wildcards).run_params


def gpu_request(stage):
    """Resource function: 1 GPU for stages the plan marks as GPU work (a model, the
    torch search), unless device is cpu.

    The SLURM executor turns it into `--gpus=1`; a cluster profile may override it.
    """

    def request(wildcards):
        uses_gpu = planned(stage, wildcards).run_params.get("uses_gpu", False)
        return int(uses_gpu and CONFIG["device"] != "cpu")

    return request


def dataset_entry(name):
    if name not in CONFIG["datasets"]:
        raise PlanError(unknown_dataset(name, CONFIG))
    return CONFIG["datasets"][name]


@cache
def dataset_files(name):
    if name in PLAN.dataset_files:  # listed while planning
        return PLAN.dataset_files[name]
    try:
        return list_dataset(CONFIG["data_root"], name, dataset_entry(name))
    except Exception:
        # Raised while Snakemake builds the DAG, where `onerror` does not run.
        if RUNS_JOBS:
            for table in withdraw_reports(PREFIX, name):
                print(f"vprflow: {table} withdrawn: dataset {name!r} cannot be listed")
        raise


def replan():
    """Plan the config again once a download laid a dataset out: its stores get the keys
    of its images, every other key stays as it was (same config, same files)."""
    memo_size = len(_memo)
    fresh = build_plan(
        CONFIG,
        _memo,
        allow_missing_checkpoints=_allow_missing,
        configfiles=workflow.configfiles,
    )
    vars(PLAN).update(vars(fresh))
    dataset_files.cache_clear()
    if len(_memo) != memo_size:
        save_fingerprints(_memo, PREFIX + FINGERPRINTS)
    if not PLAN.checkpoint_error:
        write_index(PLAN, PREFIX)


def downloaded(name):
    """First call of an input function that reads dataset ``name``'s stores. A sample
    dataset awaiting its download makes Snakemake schedule the `download` checkpoint
    (in a dry run: show it) and call again once it ran, with the dataset planned. A name
    that is no dataset of the config (a mistyped target) is named here, with the datasets
    there are."""
    dataset_entry(name)
    if name not in AWAITING_DOWNLOAD:
        return
    entry = dataset_entry(name)
    folder = dataset_folder(CONFIG["data_root"], entry)
    record = Path(PREFIX + DOWNLOAD_RECORD.format(dataset=name))
    if RUNS_JOBS and not folder.is_dir() and record.exists():
        # Its folder is gone (or data_root moved): the record no longer holds, and left
        # in place it would stand for a download that has not happened.
        record.unlink()
        print(
            f"vprflow: removed {record}: {folder}, where it records a download, is gone"
        )
    checkpoints.download.get(dataset=name)
    if not folder.is_dir():
        raise PlanError(
            f"dataset {name!r}: folder {folder} does not exist, though {record} records "
            "a download there; a run without -n (--dry-run) fetches it again"
        )
    AWAITING_DOWNLOAD.discard(name)
    replan()


def data_root_param(wildcards, output):
    """Where the images are read from. A params function that takes `output` is not a
    rerun trigger for Snakemake: moving the data folder changes no key, so it must
    rebuild nothing (a dataset's key covers its contents)."""
    return CONFIG["data_root"]


def dataset_shard_ranges(name, stage):
    """``(start, stop)`` image ranges of a sharded stage's jobs on dataset ``name``."""
    files = dataset_files(name)
    return shard_ranges(stage, len(files.reference), len(files.query), CONFIG)


def shard_inputs(wildcards):
    """The shards a per-image stage is gathered from, in image order."""
    stage = planned(wildcards.stage, wildcards)
    pattern = shard_pattern(wildcards.stage)
    # A finished store's own shards: a new shard size shapes no result.
    ranges = built_shard_ranges(
        PREFIX + store_path(wildcards.stage, wildcards.key)
    ) or dataset_shard_ranges(stage.dataset, wildcards.stage)
    return [
        pattern.format(key=wildcards.key, start=start, stop=stop)
        for start, stop in ranges
    ]


def gather_record(wildcards):
    return planned(wildcards.stage, wildcards).record


def prediction_inputs(wildcards):
    dataset_entry(wildcards.dataset)  # an unknown dataset fails here, by name
    downloaded(wildcards.dataset)
    return {
        "dataset": store_path("dataset", PLAN.dataset_keys[wildcards.dataset]),
        "recalls": [
            store_path("recall", run.recall_key) for run in PLAN.runs[wildcards.dataset]
        ],
        "mark": tables_mark(PREFIX, wildcards.dataset),
    }


def published_input(wildcards):
    """The recall table beside which a preset's published rows go; a dataset that is no
    preset fails here, before its table is built."""
    if wildcards.dataset not in presets():
        raise PlanError(
            f"results/published_{wildcards.dataset}.csv: dataset {wildcards.dataset!r} "
            f"is not a vprflow preset, so it has no published rows (docs/datasets.md "
            f"lists the presets)"
        )
    return RECALL_CSV.format(dataset=wildcards.dataset)


def published_differences(wildcards):
    """Params function: by method, how this run makes a preset's published rows otherwise
    than the published setting (the preset with the config shipped beside the workflow).
    """
    name = wildcards.dataset
    if name not in presets() or name not in PLAN.runs:
        return {}
    methods = [entry["row"] for entry in presets()[name].published if entry.get("row")]
    try:
        reference = published_plan(config, SHIPPED_CONFIG, name, SCHEMA, _memo)
    except Exception as error:  # named in the table, beside each row
        reference = error
    return published_changes(PLAN, reference, name, methods)


def report_inputs(wildcards):
    """The recall stores of a dataset's table; a dataset without ground truth has no
    table, and asking for one says so."""
    if dataset_entry(wildcards.dataset)["ground_truth"]["kind"] == "none":
        raise PlanError(
            f"dataset {wildcards.dataset!r} has ground_truth kind 'none': there is no "
            f"recall to tabulate. Its rankings are in "
            f"{PREDICTIONS_CSV.format(dataset=wildcards.dataset)} (`snakemake` builds them "
            "and its figures when the dataset is in `targets`)"
        )
    # The table brings the per-query predictions along: a table whose rankings are
    # missing could not be checked query by query.
    return {
        **prediction_inputs(wildcards),
        "predictions": PREDICTIONS_CSV.format(dataset=wildcards.dataset),
    }


def report_runs(wildcards):
    return [
        {"method": run.method, "params": run.row_params}
        for run in PLAN.runs[wildcards.dataset]
    ]


def default_targets():
    """What `snakemake` without a target builds: every output of the `targets` datasets."""
    paths = [path for name in CONFIG["targets"] for path in dataset_outputs(PLAN, name)]
    for path in paths:
        check_inside_outputs(path)  # names are plain (the schema): belt and braces
    return paths


def figure_pattern(figure):
    return FIGURE.replace("{figure}", figure)


def figure_stores(figure):
    """Input function: the stores one method's figure reads, by name."""

    def inputs(wildcards):
        downloaded(wildcards.dataset)
        return figure_inputs(PLAN, wildcards.dataset, wildcards.method, figure)

    return inputs


def pairs_stores(wildcards):
    """Input function: the dataset and recall stores of a method's (or re-ranked row's)
    pairs files, and the descriptors (and segment search) that rank past the recall's
    depth."""
    downloaded(wildcards.dataset)
    stores = method_stores(PLAN, wildcards.dataset, wildcards.method)
    names = ("dataset", "recall", "descriptors", "search")
    return {name: stores[name] for name in names if name in stores}


def export_stores(wildcards):
    """Input function: the images and descriptors stores of a method's export (no
    ground truth: a ground-truth change leaves it as it is)."""
    downloaded(wildcards.dataset)
    stores = method_stores(PLAN, wildcards.dataset, wildcards.method)
    return {name: stores[name] for name in ("images", "descriptors")}
