"""Where everything lives: stores, shards, logs, tables, figures, the index and memo.

Rules take their outputs and logs from these, input functions their inputs: one place
decides each path. Every path is relative to the working directory (a host workflow's
module ``prefix`` goes in front).
"""

from __future__ import annotations

CACHE = "results/cache"
# Per-dataset tables written by the report rule.
RECALL_CSV = "results/recall_{dataset}.csv"
PREDICTIONS_CSV = "results/predictions_{dataset}.csv"
# Figures of the report (not stages: no key, a changed figure setting reruns only them).
RECALL_PLOT = "results/plots/recall_{dataset}.png"
RECALL_TABLE = "results/tables/recall_{dataset}.html"
# A method's descriptors of a dataset in one NumPy file (the `export` rule).
EXPORT = "results/export/{dataset}/{method}.npz"
FIGURE = "results/figures/{dataset}/{figure}/{method}.png"
# Every store of the current config with its stage, datasets, methods and log folder.
INDEX = f"{CACHE}/index.tsv"
# The memo of content hashes (vprflow.fingerprints).
FINGERPRINTS = f"{CACHE}/fingerprints.json"
# A published vocabulary (vprflow.vocabularies), fetched once; one may be put there by hand.
PUBLISHED_VOCABULARY = "results/downloads/vocabularies/{name}/c_centers.pt"


def store_pattern(stage: str) -> str:
    """A stage's store, wildcard ``{key}``."""
    return f"{CACHE}/{stage}/{{key}}.zarr"


def store_path(stage: str, key: str) -> str:
    return store_pattern(stage).format(key=key)


def shard_pattern(stage: str) -> str:
    """One shard of a per-image stage, wildcards ``{key}``, ``{start}``, ``{stop}``."""
    return f"{CACHE}/{stage}/{{key}}.shards/{{start}}-{{stop}}.zarr"


def log_pattern(stage: str, part: str = "{stage}") -> str:
    """A stage's log: every log of one store (its shards, its gather) in one folder,
    ``logs/<stage>/<key>/``; ``logs/by-method/`` links to them by dataset and method."""
    return f"logs/{stage}/{{key}}/{part.replace('{stage}', stage)}.log"


def benchmark_pattern(stage: str, part: str = "{stage}") -> str:
    """A stage's benchmark table, next to its log."""
    return log_pattern(stage, part).removesuffix(".log") + ".benchmark.tsv"
