"""What a preset's row of this run does differently from the published setting.

``results/published_<preset>.csv`` sets the paper's number beside the row of the vprflow
method that reproduces it. That row is only comparable where it was made as the
preset makes it: the preset's entry (``data/presets.yaml``) with the components of the
config shipped beside the workflow (``config/config.yaml``: DINOv2 ViT-G/14 layer 31,
SAM ViT-H, the published vocabulary and PCA, ...). :func:`published_plan` plans that
setting and :func:`setting_changes` compares the two plans' stages, one method at a
time: every stage parameter that shapes the row (features, segments, vocabulary, PCA,
descriptors, search, recall, ...) and differs is named, read from the stages' records,
the one place that decides what each stage computes. A component the shipped config
does not define (a trained method of config/trained.yaml) is taken as this run defines it.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

import yaml

from vprflow.core.errors import PlanError
from vprflow.planning.config import validate_config
from vprflow.planning.plan import Plan, build_plan, method_run

# Sections of named entries: the shipped config's entries win, the run's others join.
NAMED_SECTIONS = ("backbones", "segmenters", "methods", "rerankers")
# Settings of the run, not of the published setting: where the data is, which rows run.
RUN_SETTINGS = ("data_root", "trained_baselines")
# A stage parameter naming what kind of thing the stage computes: when it differs, the
# stage's other parameters differ with it and go unnamed.
KIND_KEYS = ("backbone", "segmenter", "aggregator", "source", "kind", "index")


def reference_config(raw: dict, shipped: dict | None, preset: str) -> dict:
    """The raw config of the published setting of ``preset``: the shipped config (or,
    without one, this run's) with the run's data and the entries the shipped one lacks,
    and the preset's entry as the preset gives it."""
    base = shipped if shipped is not None else raw
    reference = {k: copy.deepcopy(v) for k, v in base.items() if k != "datasets"}
    for key in RUN_SETTINGS:
        if key in raw:
            reference[key] = copy.deepcopy(raw[key])
    for key in NAMED_SECTIONS:
        if isinstance(raw.get(key), dict):
            reference[key] = {**copy.deepcopy(raw[key]), **(reference.get(key) or {})}
    reference["datasets"] = {preset: {}}
    reference["targets"] = [preset]
    return reference


def published_plan(
    raw: dict, shipped_path: str | Path, preset: str, schema: str | Path, memo: dict
) -> Plan:
    """The plan of ``preset`` alone in its published setting (:func:`reference_config`;
    ``shipped_path``: the workflow's config/config.yaml, if it exists)."""

    shipped_path = Path(shipped_path)
    shipped = yaml.safe_load(shipped_path.read_text()) if shipped_path.is_file() else None
    config = validate_config(reference_config(raw, shipped, preset), schema)
    config["datasets"] = {preset: config["datasets"][preset]}
    return build_plan(config, memo, allow_missing_checkpoints=True)


def setting_changes(plan: Plan, reference: Plan, dataset: str, method: str) -> list[str]:
    """Each stage of ``method``'s row on ``dataset`` whose parameters differ from the row
    of the same method in ``reference`` (:func:`published_plan`), with the parameters
    and both values: ``features: backbone daisy (published: dinov2)``. A stage only one
    of the two has is named as such. Empty where the row is made as published."""
    ours = _stages(plan, method_run(plan, dataset, method).recall_key)
    theirs = _stages(reference, method_run(reference, dataset, method).recall_key)
    names = _names(ours.keys() | theirs.keys())
    changes = []
    for label in sorted(ours.keys() | theirs.keys(), key=lambda k: (k.count("/"), k)):
        name = names[label]
        if label not in theirs:
            changes.append(f"{name}: not in the published setting")
        elif label not in ours:
            changes.append(f"{name}: none (published: {_show_params(theirs[label])})")
        elif ours[label] != theirs[label]:
            changes.append(f"{name}: {_difference(ours[label], theirs[label])}")
    return changes


def published_changes(plan: Plan, reference: Plan | Exception, dataset: str, methods) -> dict:
    """``{method: text}`` for the rows ``methods`` of ``dataset`` (those published rows
    name) that this run makes otherwise than the published setting: what differs, or why
    the published setting could not be planned (``reference`` is then that error)."""
    planned = {run.method for run in plan.runs.get(dataset, [])}
    changes = {}
    for method in methods:
        if method not in planned:
            continue
        if isinstance(reference, Exception):
            changes[method] = f"the published setting could not be planned ({reference})"
            continue
        try:
            found = setting_changes(plan, reference, dataset, method)
        except PlanError as error:  # no such row in the published setting
            found = [f"the published setting has no such row ({error})"]
        if found:
            changes[method] = "; ".join(found)
    return changes


def _stages(plan: Plan, recall_key: str) -> dict[str, dict]:
    """The stages a recall store is made from, each by the stage names on its shortest
    path from the recall (``recall/descriptors/features``), as its parameters."""
    found: dict[str, dict] = {}
    seen: dict[tuple[str, str], str] = {}
    frontier = [("recall", ("recall", recall_key))]
    while frontier:
        label, ref = frontier.pop(0)  # breadth first: each stage's shortest path
        if ref in seen:
            continue
        seen[ref] = label
        stage = plan.get(*ref)
        found.setdefault(label, stage.record["params"])
        for upstream in sorted(stage.inputs.values()):
            frontier.append((f"{label}/{upstream[0]}", upstream))
    return found


def _names(labels) -> dict[str, str]:
    """A label's name for a message: its stage, or its path where two labels end in the
    same stage (a re-ranker's features beside the method's)."""
    last = [label.rsplit("/", 1)[-1] for label in labels]
    return {
        label: label if last.count(label.rsplit("/", 1)[-1]) > 1 else label.rsplit("/", 1)[-1]
        for label in labels
    }


def _flat(params: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in params.items():
        if isinstance(value, dict) and value:
            out.update(_flat(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def _show(value) -> str:
    if isinstance(value, list):
        return " x ".join(map(str, value)) if len(value) == 2 else " ".join(map(str, value))
    return value if isinstance(value, str) else json.dumps(value)


def _difference(ours: dict, theirs: dict) -> str:
    ours, theirs = _flat(ours), _flat(theirs)
    keys = sorted(k for k in ours.keys() | theirs.keys() if ours.get(k) != theirs.get(k))
    kinds = [k for k in keys if k in KIND_KEYS]
    return ", ".join(
        f"{k} {_show(ours.get(k, 'unset'))} (published: {_show(theirs.get(k, 'unset'))})"
        for k in (kinds or keys)
    )


def _show_params(params: dict) -> str:
    flat = _flat(params)
    kinds = [k for k in flat if k in KIND_KEYS]
    return ", ".join(f"{k} {_show(flat[k])}" for k in (kinds or sorted(flat)))
