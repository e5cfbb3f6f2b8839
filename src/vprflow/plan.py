"""From a validated config to the content-addressed stages of every experiment.

Each stage instance is identified by a key: a short hash of exactly the parameters
that shape its output, the keys of its inputs and a per-stage format version.
Outputs live at ``results/cache/<stage>/<key>.zarr``. Two experiments that agree on
a stage's parameters and inputs get the same key and share the store; changing a
parameter changes the key of that stage and of everything downstream only.

Bump a stage's entry in :data:`FORMAT_VERSIONS` whenever the code changes what the
stage writes: Snakemake does not track the library's source, only the key does.
"""

from __future__ import annotations

import copy
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

CACHE = "results/cache"

FORMAT_VERSIONS = {
    "dataset": 1,
    "features": 2,  # 2: crop offsets round like torchvision
    "segments": 1,
    "vocabulary": 1,
    "pca": 1,
    "descriptors": 2,  # 2: crop_aligned uses the backbone's crop offsets
    "recall": 1,
}

# Settings that change how a stage runs but not what it computes: kept out of keys.
EXECUTION_ONLY = ("batch_size",)


class PlanError(ValueError):
    """A config that passes the schema but refers to something that does not exist."""


def content_key(record: dict) -> str:
    """16 hex digits of the SHA-256 of ``record`` as canonical JSON."""
    text = json.dumps(record, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def file_digest(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def deep_merge(base: dict, override: dict) -> dict:
    merged = copy.deepcopy(base)
    for name, value in override.items():
        if isinstance(value, dict) and isinstance(merged.get(name), dict):
            merged[name] = deep_merge(merged[name], value)
        else:
            merged[name] = copy.deepcopy(value)
    return merged


def store_path(stage: str, key: str) -> str:
    return f"{CACHE}/{stage}/{key}.zarr"


@dataclass
class Stage:
    """One stage instance: what it computes from which upstream stores."""

    stage: str
    key: str
    params: dict  # exactly what was hashed (plus execution-only settings, see run_params)
    inputs: dict[str, tuple[str, str]]  # input name -> (stage, key)
    run_params: dict = field(default_factory=dict)  # not hashed: device, batch size
    dataset: str = ""

    @property
    def path(self) -> str:
        return store_path(self.stage, self.key)

    def input_paths(self) -> dict[str, str]:
        return {name: store_path(*ref) for name, ref in self.inputs.items()}


@dataclass
class MethodRun:
    """One row of a results table: a method on a dataset."""

    method: str
    recall_key: str
    row_params: dict  # flattened parameters for the CSV


@dataclass
class Plan:
    stages: dict[str, dict[str, Stage]] = field(default_factory=dict)
    runs: dict[str, list[MethodRun]] = field(default_factory=dict)  # dataset -> rows
    dataset_keys: dict[str, str] = field(default_factory=dict)

    def add(
        self,
        stage: str,
        params: dict,
        inputs: dict[str, tuple[str, str]],
        dataset: str,
        run_params: dict | None = None,
    ) -> str:
        record = {
            "stage": stage,
            "version": FORMAT_VERSIONS[stage],
            "params": params,
            "inputs": {name: key for name, (_, key) in sorted(inputs.items())},
        }
        key = content_key(record)
        self.stages.setdefault(stage, {})[key] = Stage(
            stage, key, record, inputs, run_params or {}, dataset
        )
        return key

    def get(self, stage: str, key: str) -> Stage:
        try:
            return self.stages[stage][key]
        except KeyError:
            raise PlanError(
                f"no {stage} stage with key {key} in the current config "
                f"(stale target? keys change whenever parameters do)"
            ) from None


def _flatten(prefix: str, value, out: dict) -> None:
    if isinstance(value, dict):
        for name in sorted(value):
            _flatten(f"{prefix}.{name}" if prefix else name, value[name], out)
    elif isinstance(value, list):
        out[prefix] = " ".join(str(v) for v in value)
    else:
        out[prefix] = value


def _hashed(params: dict) -> dict:
    return {k: v for k, v in params.items() if k not in EXECUTION_ONLY}


def _resolution(dataset: dict, profile: dict) -> list[int]:
    if profile.get("resolution", "dataset") == "dataset":
        return list(dataset["resolution"])
    return list(profile["resolution"])


METHOD_SECTIONS = ("features", "segmenter", "vocabulary", "pca", "segvlad", "snsm", "pooling")

# Model a backbone or segmenter entry uses when it names none.
DEFAULT_MODELS = {
    "dinov2": "facebook/dinov2-giant",
    "dino": "facebook/dino-vitb8",
    "sam": "facebook/sam-vit-huge",
}


def resolve_method(config: dict, name: str, dataset: dict | None = None) -> dict:
    """A method's settings: top-level defaults, then the dataset's ``defaults``, then
    the method's own overrides (later wins, dictionaries merge key by key)."""
    if name not in config["methods"]:
        raise PlanError(f"unknown method {name!r}; defined methods: {sorted(config['methods'])}")
    settings = {section: config[section] for section in METHOD_SECTIONS}
    settings = deep_merge(settings, (dataset or {}).get("defaults", {}))
    return deep_merge(settings, config["methods"][name])


def source_fingerprint(entry: dict, memo: dict) -> dict:
    """What identifies the weights or file a backbone/segmenter entry reads.

    Hub ids stand for themselves; local model directories and imported HDF5 files are
    hashed by content (memoised by path, size and modification time, because a
    ViT-G checkpoint takes seconds to hash and the plan is built on every run).
    """
    kind = entry.get("backbone", entry.get("segmenter"))
    if kind == "import":
        return {"file_sha256": _memoised(entry["file"], memo, file_digest)}
    if kind in DEFAULT_MODELS:
        from vprflow.models import is_local_model, weights_fingerprint

        model = entry.get("model", DEFAULT_MODELS[kind])
        if not is_local_model(model):
            return {"model": model, "weights": f"hf:{model}"}
        return {"model": model, "weights": _memoised(model, memo, weights_fingerprint)}
    return {}


def _memoised(path: str, memo: dict, digest) -> str:
    target = Path(path)
    if not target.exists():
        raise PlanError(f"{path} does not exist")
    files = sorted(target.iterdir()) if target.is_dir() else [target]
    stamp = "|".join(
        f"{f.name}:{f.stat().st_size}:{f.stat().st_mtime_ns}" for f in files if f.is_file()
    )
    memo_key = f"{target.resolve()}|{stamp}"
    if memo_key not in memo:
        memo[memo_key] = digest(str(target))
    return memo[memo_key]


def build_plan(config: dict, memo: dict | None = None) -> Plan:
    """Every stage of every (dataset, method) pair in ``config``; shared stages dedupe.

    ``memo`` caches content hashes of local model weights and imported files across
    runs (see :func:`source_fingerprint`); pass a dict loaded from disk to reuse it.
    """
    memo = {} if memo is None else memo
    plan = Plan()
    execution = {"device": config["device"]}
    for dataset_name, dataset in sorted(config["datasets"].items()):
        dataset_params = {
            "name": dataset_name,
            **{k: dataset[k] for k in ("path", "reference", "query", "paired", "ground_truth")},
        }
        dataset_key = plan.add("dataset", dataset_params, {}, dataset_name)
        plan.dataset_keys[dataset_name] = dataset_key
        rows = []
        for method_name in dataset["methods"]:
            method = resolve_method(config, method_name, dataset)
            rows.append(
                _plan_method(
                    plan,
                    config,
                    dataset_name,
                    dataset,
                    dataset_key,
                    method_name,
                    method,
                    execution,
                    memo,
                )
            )
        plan.runs[dataset_name] = rows
    return plan


def _named_entry(config: dict, section: str, name: str, method_name: str) -> dict:
    if name not in config[section]:
        raise PlanError(
            f"method {method_name!r} uses {name!r}, which is not defined under {section}: "
            f"{sorted(config[section])}"
        )
    return config[section][name]


def _plan_method(
    plan, config, dataset_name, dataset, dataset_key, method_name, method, execution, memo
):
    aggregator = method["aggregator"]
    features_name = method["features"]
    backbone = _named_entry(config, "backbones", features_name, method_name)
    ds = ("dataset", dataset_key)
    features_params = {
        **_hashed(backbone),
        **source_fingerprint(backbone, memo),
        "resolution": _resolution(dataset, backbone),
    }
    features_key = plan.add(
        "features",
        features_params,
        {"dataset": ds},
        dataset_name,
        {**execution, "batch_size": backbone.get("batch_size", 1)},
    )
    fx = ("features", features_key)
    row = {"aggregator": aggregator, "features": features_name, **_prefixed("features", backbone)}
    inputs = {"dataset": ds, "features": fx}

    def vocabulary_stage():
        vocabulary = method["vocabulary"]
        params = {k: v for k, v in vocabulary.items() if k != "file"}
        if vocabulary["source"] == "file":
            params.update(
                file=vocabulary["file"], sha256=_memoised(vocabulary["file"], memo, file_digest)
            )
        row.update(_prefixed("vocabulary", vocabulary))
        return (
            "vocabulary",
            plan.add("vocabulary", params, {"dataset": ds, "features": fx}, dataset_name),
        )

    if aggregator == "segvlad":
        segmenter_name = method["segmenter"]
        segmenter = _named_entry(config, "segmenters", segmenter_name, method_name)
        segments_params = {
            **_hashed(segmenter),
            **source_fingerprint(segmenter, memo),
            "resolution": _segment_resolution(dataset, segmenter),
        }
        sx = (
            "segments",
            plan.add("segments", segments_params, {"dataset": ds}, dataset_name, execution),
        )
        vx = vocabulary_stage()
        segvlad = method["segvlad"]
        graph = {k: segvlad[k] for k in ("mask_to_patch", "small_graph")}
        inputs.update(segments=sx, vocabulary=vx)
        pca = method["pca"]
        if pca["enabled"]:
            pca_params = {**{k: v for k, v in pca.items() if k != "enabled"}, **graph}
            inputs["pca"] = ("pca", plan.add("pca", pca_params, dict(inputs), dataset_name))
            row.update(_prefixed("pca", pca))
        else:
            row["pca.enabled"] = False
        descriptor_params = {"aggregator": "segvlad", "order": segvlad["order"], **graph}
        row.update(segmenter=segmenter_name, **_prefixed("segmenter", segmenter))
        row.update(_prefixed("segvlad", segvlad))
    elif aggregator == "anyloc_vlad":
        inputs["vocabulary"] = vocabulary_stage()
        descriptor_params = {"aggregator": aggregator}
    elif aggregator == "snsm":
        descriptor_params = {"aggregator": aggregator, **method["snsm"]}
        row.update(_prefixed("snsm", method["snsm"]))
    else:
        descriptor_params = {"aggregator": aggregator}
        if aggregator == "gem":
            descriptor_params["p"] = method["pooling"]["gem_p"]
            row["pooling.gem_p"] = method["pooling"]["gem_p"]
    descriptors_key = plan.add("descriptors", descriptor_params, inputs, dataset_name)
    recall_params = {
        "recall_at": dataset["recall_at"],
        "top_k": max(max(dataset["recall_at"]), 20),
        "top_segments": method["segvlad"]["top_segments"] if aggregator == "segvlad" else None,
    }
    if aggregator == "segvlad":
        row["segvlad.top_segments"] = method["segvlad"]["top_segments"]
    recall_key = plan.add(
        "recall",
        recall_params,
        {"dataset": ds, "descriptors": ("descriptors", descriptors_key)},
        dataset_name,
    )
    return MethodRun(method_name, recall_key, _flat(row))


def _segment_resolution(dataset: dict, segmenter: dict) -> list[int]:
    if segmenter.get("resolution") not in (None, "dataset"):
        return list(segmenter["resolution"])
    width, height = dataset["resolution"]
    scale = segmenter.get("resolution_scale", 0.5)
    return [max(1, round(width * scale)), max(1, round(height * scale))]


def _prefixed(prefix: str, section: dict) -> dict:
    return {f"{prefix}.{k}": v for k, v in section.items() if k not in EXECUTION_ONLY}


def _flat(row: dict) -> dict:
    out: dict = {}
    for name, value in row.items():
        _flatten(name, value, out)
    return out
