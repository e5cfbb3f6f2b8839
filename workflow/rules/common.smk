# Config validation, the content-addressed plan, and the input functions every rule uses.
from functools import cache
from pathlib import Path

from vprflow.config import validate_config
from vprflow.datasets import list_dataset
from vprflow.plan import (
    CACHE,
    PREDICTIONS_CSV,
    RECALL_CSV,
    PlanError,
    build_plan,
    load_fingerprints,
    save_fingerprints,
    withdraw_stale_reports,
)


configfile: "config/config.yaml"


CONFIG = validate_config(config, Path(workflow.basedir) / "config" / "schema.yaml")
# Content hashes of images, local model weights and imported files, memoised between runs.
_memo = load_fingerprints()
_memo_size = len(_memo)
PLAN = build_plan(CONFIG, _memo)
if len(_memo) != _memo_size:
    save_fingerprints(_memo)
# Backbones and segmenters that run a neural network (and so want a GPU).
MODEL_KINDS = {"dinov2", "dino", "sam"}
SHARDED = "features|segments|descriptors"


wildcard_constraints:
    key="[0-9a-f]{16}",
    start=r"\d+",
    stop=r"\d+",


def planned(stage, wildcards):
    return PLAN.get(stage, wildcards.key)


def stage_inputs(stage):
    """Input function: the upstream stores of a stage instance, by name."""
    return lambda wildcards: planned(stage, wildcards).input_paths()


def stage_params(stage):
    """Params function: the stage's hashed record (what its key is made of)."""
    return lambda wildcards: planned(stage, wildcards).params


def stage_run_params(stage):
    """Execution settings that do not shape the output (device, batch size)."""
    return lambda wildcards: planned(stage, wildcards).run_params


def gpu_request(stage):
    """Resource function: 1 GPU for stages that run a model, unless device is cpu.

    The SLURM executor turns it into `--gpus=1`; a cluster profile may override it.
    """

    def request(wildcards):
        params = planned(stage, wildcards).params["params"]
        kind = params.get("backbone", params.get("segmenter"))
        return int(kind in MODEL_KINDS and CONFIG["device"] != "cpu")

    return request


def dataset_spec(name):
    if name not in CONFIG["datasets"]:
        raise PlanError(
            f"unknown dataset {name!r}; configured: {sorted(CONFIG['datasets'])}"
        )
    return CONFIG["datasets"][name]


@cache
def dataset_files(name):
    return list_dataset(CONFIG["data_root"], name, dataset_spec(name))


def data_root_param(wildcards, output):
    """Where the images are read from. A params function that takes `output` is not a
    rerun trigger for Snakemake: moving the data folder changes no key, so it must
    rebuild nothing (a dataset's key covers its contents)."""
    return CONFIG["data_root"]


def shard_ranges(name):
    files = dataset_files(name)
    n_images = len(files.reference) + len(files.query)
    size = CONFIG["shard_size"] or n_images
    return [(start, min(start + size, n_images)) for start in range(0, n_images, size)]


def shard_inputs(wildcards):
    """The shards a per-image stage is gathered from, in image order."""
    stage = planned(wildcards.stage, wildcards)
    return [
        f"{CACHE}/{wildcards.stage}/{wildcards.key}.shards/{start}-{stop}.zarr"
        for start, stop in shard_ranges(stage.dataset)
    ]


def gather_params(wildcards):
    return planned(wildcards.stage, wildcards).params


def report_inputs(wildcards):
    dataset_spec(wildcards.dataset)  # an unknown dataset fails here, by name
    return {
        "dataset": f"{CACHE}/dataset/{PLAN.dataset_keys[wildcards.dataset]}.zarr",
        "recalls": [
            f"{CACHE}/recall/{run.recall_key}.zarr"
            for run in PLAN.runs[wildcards.dataset]
        ],
    }


def report_runs(wildcards):
    return [
        {"method": run.method, "params": run.row_params}
        for run in PLAN.runs[wildcards.dataset]
    ]
