# Config validation, the content-addressed plan, and the input functions every rule uses.
import json
from functools import cache
from pathlib import Path

from vprflow.config import validate_config
from vprflow.datasets import ground_truth_files, list_dataset
from vprflow.plan import CACHE, PlanError, build_plan


configfile: "config/config.yaml"


CONFIG = validate_config(config, Path(workflow.basedir) / "config" / "schema.yaml")
# Content hashes of local model weights / imported files, memoised between runs.
FINGERPRINTS = Path(CACHE) / "fingerprints.json"
_memo = json.loads(FINGERPRINTS.read_text()) if FINGERPRINTS.exists() else {}
_memo_size = len(_memo)
PLAN = build_plan(CONFIG, _memo)
if len(_memo) != _memo_size:
    FINGERPRINTS.parent.mkdir(parents=True, exist_ok=True)
    FINGERPRINTS.write_text(json.dumps(_memo, indent=1, sort_keys=True))
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


def dataset_inputs(wildcards):
    """The dataset stage reads every image and the ground-truth file."""
    name = planned("dataset", wildcards).dataset
    files = dataset_files(name)
    return [
        *files.reference,
        *files.query,
        *ground_truth_files(CONFIG["data_root"], dataset_spec(name)),
    ]


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
