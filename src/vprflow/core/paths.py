"""Where everything lives: stores, shards, logs, tables, figures, the index and memo.

Rules take their outputs and logs from these, input functions their inputs: one place
decides each path. Every path is relative to the working directory (a host workflow's
module ``prefix`` goes in front).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

CACHE = "results/cache"
# Per-dataset tables, written by the recall_csv and predictions rules.
RECALL_CSV = "results/recall_{dataset}.csv"
PREDICTIONS_CSV = "results/predictions_{dataset}.csv"
# A preset's published recall beside the run's (the `published` rule).
PUBLISHED_CSV = "results/published_{dataset}.csv"
# Figures of the report (not stages: no key, a changed figure setting reruns only them).
RECALL_PLOT = "results/plots/recall_{dataset}.png"
RECALL_TABLE = "results/tables/recall_{dataset}.html"
# A method's descriptors of a dataset in one NumPy file (the `export` rule).
EXPORT = "results/export/{dataset}/{method}.npz"
# A method's (or re-ranked row's) retrievals for localisation (the `pairs` rule): hloc's
# pairs file and kapture's (SNSM's predictions.txt).
PAIRS = "results/pairs/{dataset}/{method}/pairs.txt"
KAPTURE_PAIRS = "results/pairs/{dataset}/{method}/predictions.txt"
FIGURE = "results/figures/{dataset}/{figure}/{method}.png"
# Every store of the current config with its stage, datasets, methods and log folder.
INDEX = f"{CACHE}/index.tsv"
# An empty file each dataset's tables read, touched when they must be rebuilt
# (vprflow.planning.reports.mark_stale_tables).
TABLES_MARK = f"{CACHE}/marks/{{dataset}}"
# The memo of content hashes (vprflow.planning.fingerprints).
FINGERPRINTS = f"{CACHE}/fingerprints.json"
# What `snakemake <DOWNLOAD_RECORD>` builds (vprflow.data.download): the record written once a
# dataset's folder is in place, and the download's log.
DOWNLOAD_RECORD = "results/downloads/{dataset}.json"
DOWNLOAD_LOG = "logs/download/{dataset}.log"
# A published vocabulary (vprflow.aggregation.vocabularies), fetched once; one may be put
# there by hand.
PUBLISHED_VOCABULARY = "results/downloads/vocabularies/{name}/c_centers.pt"


def dataset_folder(data_root: str | Path, dataset: dict) -> Path:
    """A dataset entry's folder: its ``path`` under ``data_root``."""
    return Path(data_root) / dataset["path"]


def download_hint(name: str) -> str:
    """The command that downloads dataset ``name`` (for 'folder does not exist' errors)."""
    return f"snakemake --cores 1 {DOWNLOAD_RECORD.format(dataset=name)}"


# What a name in a path may be: a dataset, method, re-ranker or backbone entry (the
# config's `name` in the schema), or a row `<method>+<reranker>`. The rules constrain
# the `dataset` and `method` wildcards to it.
NAME_PATTERN = r"[A-Za-z0-9][A-Za-z0-9_.+-]*"
# Every output lives under one of these (relative to the working directory).
OUTPUT_ROOTS = ("results", "logs")


def check_inside_outputs(path: str, names: dict | None = None) -> None:
    """Raise ValueError unless ``path`` (relative) resolves under ``results/`` or
    ``logs/`` of the working directory; the message names ``names`` (what was filled in)."""
    here = Path(os.getcwd()).resolve()
    resolved = (here / path).resolve()
    if not Path(path).is_absolute() and any(
        resolved.is_relative_to(here / root) and resolved != here / root for root in OUTPUT_ROOTS
    ):
        return
    what = ", ".join(f"{k} {v!r}" for k, v in (names or {}).items()) or "a name"
    raise ValueError(
        f"{what} would put output at {path}, outside {' and '.join(OUTPUT_ROOTS)}/: a name "
        "in a path must be a plain name (letters, digits, _ . + -, no / or ..)"
    )


def store_pattern(stage: str) -> str:
    """A stage's store, wildcard ``{key}``."""
    return f"{CACHE}/{stage}/{{key}}.zarr"


def store_path(stage: str, key: str) -> str:
    return store_pattern(stage).format(key=key)


def shard_pattern(stage: str) -> str:
    """One shard of a per-image stage, wildcards ``{key}``, ``{start}``, ``{stop}``."""
    return f"{CACHE}/{stage}/{{key}}.shards/{{start}}-{{stop}}.zarr"


def shard_range(path: str | Path) -> tuple[int, int]:
    """The ``(start, stop)`` image range of a shard at ``path`` (:func:`shard_pattern`)."""
    match = re.fullmatch(r"(\d+)-(\d+)\.zarr", Path(path).name)
    if match is None:
        raise ValueError(f"{path}: not a shard (<start>-<stop>.zarr)")
    return int(match[1]), int(match[2])


def shard_layout(shard_paths: list[str]) -> list[list[int]]:
    """The ``[start, stop]`` image ranges of the shards a store is gathered from, in
    order: the store keeps them (its ``shards`` attribute), so that while it exists the
    workflow asks for the same shards (:func:`vprflow.stages.jobs.built_shard_ranges`)
    and a change of the shard size, which shapes no result, reruns nothing."""
    return [list(shard_range(path)) for path in shard_paths]


def log_pattern(stage: str, part: str = "{stage}") -> str:
    """A stage's log: every log of one store (its shards, its gather) in one folder,
    ``logs/<stage>/<key>/``; ``logs/by-method/`` links to them by dataset and method."""
    return f"logs/{stage}/{{key}}/{part.replace('{stage}', stage)}.log"


def benchmark_pattern(stage: str, part: str = "{stage}") -> str:
    """A stage's benchmark table, next to its log."""
    return log_pattern(stage, part).removesuffix(".log") + ".benchmark.tsv"
