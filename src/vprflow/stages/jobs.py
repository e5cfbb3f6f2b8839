"""How the rules' script, the tests and the benchmarks run a job of any stage.

A rule hands its script a :class:`Job` (the stage's hashed record, its input stores,
its output, and how to run); :func:`run_job` calls the stage's runner in
:data:`RUNNERS`, one for every stage of :data:`vprflow.planning.plan.STAGES`, with the
job. The sharding policy comes from that table: which stages run in shards, over which
image ranges (:func:`shard_ranges`); how shards become one store is
:func:`combine_shards`.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from pathlib import Path

from vprflow.core.lazy import lazy_import
from vprflow.stages.base import Job

# Every stage's module, imported when a job of it runs: a job imports only its own
# stage's dependencies (torch or faiss cost seconds), and the planner's (~50 ms a job)
# only where it needs them.
dataset = lazy_import("vprflow.stages.dataset")
features = lazy_import("vprflow.stages.features")
segments = lazy_import("vprflow.stages.segments")
vocabulary = lazy_import("vprflow.stages.vocabulary")
pca = lazy_import("vprflow.stages.pca")
descriptors = lazy_import("vprflow.stages.descriptors")
search = lazy_import("vprflow.stages.search")
matches = lazy_import("vprflow.stages.matches")
rerank = lazy_import("vprflow.stages.rerank")
recall = lazy_import("vprflow.stages.recall")
gather = lazy_import("vprflow.stages.gather")
plan = lazy_import("vprflow.planning.plan")

__all__ = [
    "RUNNERS",
    "Job",
    "built_shard_ranges",
    "combine_shards",
    "run_job",
    "shard_ranges",
]

# Every stage's runner, ``(job) -> None``: one function of its stage's module.


def _build_images(job: Job) -> None:
    dataset.build_images(job)


def _build_dataset(job: Job) -> None:
    dataset.build_dataset(job)


def _compute_features(job: Job) -> None:
    features.compute_features(job)


def _compute_segments(job: Job) -> None:
    segments.compute_segments(job)


def _fit_vocabulary(job: Job) -> None:
    vocabulary.fit_vocabulary(job)


def _fit_pca(job: Job) -> None:
    pca.fit_pca(job)


def _compute_descriptors(job: Job) -> None:
    descriptors.compute_descriptors(job)


def _compute_search(job: Job) -> None:
    search.compute_search(job)


def _compute_matches(job: Job) -> None:
    matches.compute_matches(job)


def _compute_rerank(job: Job) -> None:
    rerank.compute_rerank(job)


def _compute_recall(job: Job) -> None:
    recall.compute_recall(job)


RUNNERS: dict[str, Callable[[Job], None]] = {
    "images": _build_images,
    "dataset": _build_dataset,
    "features": _compute_features,
    "segments": _compute_segments,
    "vocabulary": _fit_vocabulary,
    "pca": _fit_pca,
    "descriptors": _compute_descriptors,
    "search": _compute_search,
    "matches": _compute_matches,
    "rerank": _compute_rerank,
    "recall": _compute_recall,
}


def run_job(job: Job) -> None:
    """Run one job of its stage (``job.record["stage"]``)."""
    RUNNERS[job.stage](job)


def shard_ranges(
    stage: str, n_reference: int, n_query: int, sizes: Mapping[str, int]
) -> list[tuple[int, int]]:
    """``(start, stop)`` image ranges of a sharded stage's jobs, in order: all images
    (references then queries) for a stage sharded over images, the reference images for
    one sharded over references, ``sizes[STAGES[stage].shard_size]`` a job (``sizes``:
    the validated config, or any mapping of its shard-size keys); a size of 0 is one
    job."""
    if stage not in plan.SHARDED:
        raise ValueError(f"stage {stage!r} is not sharded; sharded stages: {plan.SHARDED}")
    spec = plan.STAGES[stage]
    n_images = n_reference if spec.shards == "references" else n_reference + n_query
    size = sizes[spec.shard_size] or n_images
    return [(start, min(start + size, n_images)) for start in range(0, n_images, size)]


def built_shard_ranges(store: str | Path) -> list[tuple[int, int]] | None:
    """The shard ranges the gathered ``store`` was built from, while it exists (None:
    absent, or written before stores kept them). The gather rule asks for these rather
    than the configured ones: Snakemake reruns a job whose set of input files changed,
    and the shards of a finished store are gone, so a new ``shard_size`` would otherwise
    recompute every per-image stage into identical stores."""
    try:
        attrs = json.loads((Path(store) / "zarr.json").read_text()).get("attributes", {})
    except (OSError, ValueError):
        return None
    shards = attrs.get("shards")
    if not isinstance(shards, list) or not shards:
        return None
    return [(int(start), int(stop)) for start, stop in shards]


def combine_shards(shard_paths: list[str], record: dict, out: str) -> None:
    """One store from a sharded stage's shards (in order): search shards hold per-shard
    top-k lists and are merged; the others' rows are concatenated."""
    if record["stage"] == "search":
        search.merge_search(shard_paths, record, out)
    else:
        gather.gather(shard_paths, record, out)
