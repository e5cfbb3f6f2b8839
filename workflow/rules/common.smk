# The invocation (vprflow.planning.invocation: the validated config, its plan, what the
# command asked for) and the input and params functions the rules take from it.
import sys
from pathlib import Path

from vprflow.core.paths import (
    NAME_PATTERN,
    benchmark_pattern,
    log_pattern,
    shard_pattern,
    store_path,
    store_pattern,
)
from vprflow.planning.invocation import Invocation, asked
from vprflow.planning.plan import SHARDED
from vprflow.stages.jobs import built_shard_ranges, shard_ranges


configfile: "config/config.yaml"


# Found next to this file (not via workflow.basedir), so that a host workflow that
# imports vprflow as a module reads vprflow's schema and shipped config.
SCHEMA = Path(workflow.current_basedir).parent / "schemas" / "config.schema.yaml"
SHIPPED_CONFIG = Path(workflow.current_basedir).parents[1] / "config" / "config.yaml"
# A host workflow's module `prefix`: the paths planning opens itself (not via rules).
PREFIX = workflow.modifier.path_modifier.prefix or ""
# Reading this file writes nothing: the invocation writes once Snakemake builds the DAG.
INVOCATION = Invocation.read(
    config, SCHEMA, workflow.configfiles, workflow.overwrite_configfiles, PREFIX
)
CONFIG = INVOCATION.config
SHARDED_STAGES = "|".join(SHARDED)


wildcard_constraints:
    key="[0-9a-f]{16}",
    dataset=NAME_PATTERN,
    method=NAME_PATTERN,
    start=r"\d+",
    stop=r"\d+",


def started():
    """The invocation, told on the first call what the command asked for: Snakemake
    knows its targets and whether it runs jobs once it builds the DAG, when input
    functions run (vprflow.planning.invocation)."""
    if INVOCATION.command is None:
        wait = lambda name: checkpoints.download.get(dataset=name)
        INVOCATION.begin(asked(workflow, sys.argv), wait)
    return INVOCATION


def planned(stage, wildcards):
    return started().plan.get(stage, wildcards.key)


def stage_inputs(stage):
    """Input function: the upstream stores of a stage instance, by name."""
    return lambda wildcards: planned(stage, wildcards).input_paths()


def stage_record(stage):
    """Params function: the stage's hashed record (what its key is made of)."""
    return lambda wildcards: planned(stage, wildcards).record


def stage_run_params(stage):
    """Params function: how a stage instance runs (device, batch size). It takes `output`
    so that Snakemake's params trigger leaves it out: the key holds every setting that
    shapes the result, and a device or batch-size change must rerun nothing."""
    return lambda wildcards, output: planned(stage, wildcards).run_params


def gpu_request(stage):
    """Resource function: 1 GPU (`--gpus=1` under SLURM) for stages the plan marks as GPU
    work (a model, the torch search), unless device is cpu."""
    return lambda wildcards: int(
        planned(stage, wildcards).run_params.get("uses_gpu", False)
        and CONFIG["device"] != "cpu"
    )


def data_root_param(wildcards, output):
    """Where the images are read from. Taking `output`, it is no rerun trigger: moving
    the data folder changes no key (a dataset's key covers its contents)."""
    return CONFIG["data_root"]


def shard_inputs(wildcards):
    """The shards a per-image stage is gathered from, in image order: a finished store's
    own (a new shard size shapes no result), else the dataset's."""
    stage = planned(wildcards.stage, wildcards)
    ranges = built_shard_ranges(PREFIX + store_path(wildcards.stage, wildcards.key))
    if not ranges:
        files = INVOCATION.dataset_files(stage.dataset)
        ranges = shard_ranges(
            wildcards.stage, len(files.reference), len(files.query), CONFIG
        )
    pattern = shard_pattern(wildcards.stage)
    return [pattern.format(key=wildcards.key, start=a, stop=b) for a, b in ranges]


def gather_record(wildcards):
    return planned(wildcards.stage, wildcards).record


def prediction_inputs(wildcards):
    return started().prediction_inputs(wildcards.dataset)


def report_inputs(wildcards):
    return started().table_inputs(wildcards.dataset)


def report_runs(wildcards):
    return started().table_rows(wildcards.dataset)


def published_input(wildcards):
    return started().published_table(wildcards.dataset)


def published_differences(wildcards):
    """Params function: how this run makes a preset's published rows otherwise than the
    published setting (the preset with the config shipped beside the workflow)."""
    return started().published_differences(
        wildcards.dataset, config, SHIPPED_CONFIG, SCHEMA
    )


def published_checkpoint(output):
    """A trained checkpoint's published file, for the rule that fetches it."""
    return started().plan.checkpoints[output[0]].published


def method_stores_of(*names):
    """Input function: the stores of one method's row, by name."""
    return lambda wildcards: started().method_stores(
        wildcards.dataset, wildcards.method, names
    )


def figure_stores(figure):
    """Input function: the stores one method's figure reads, by name."""
    return lambda wildcards: started().figure_stores(
        wildcards.dataset, wildcards.method, figure
    )
