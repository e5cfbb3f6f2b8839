"""One job of a stage, and the table of stage runners that the workflow's scripts, the
tests and the benchmarks share.

A rule hands its script a :class:`Job` (the stage's hashed record, its input stores,
its output, and how to run); :func:`run_job` finds the stage's function in
:data:`RUNNERS` by ``record["stage"]``. The sharding policy is here too: which stages
run in shards, over which image ranges (:func:`shard_ranges`), and how shards are
combined into one store (:func:`combine_shards`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Job:
    """What one job of a stage needs.

    ``record`` is the stage's hashed record (:class:`vprflow.planning.plan.Stage`); ``inputs``
    its upstream stores by name; ``start``/``stop`` the image range of a sharded
    stage's job (references first, then queries; for ``search``, reference images);
    ``data_root``, ``device`` and ``batch_size`` do not shape the output.
    """

    record: dict
    inputs: dict[str, str]
    out: str
    start: int | None = None
    stop: int | None = None
    data_root: str = ""
    run: dict = field(default_factory=dict)  # the plan's run_params: device, batch_size
    threads: int = 1
    fingerprints: str | None = None  # the images and dataset stages' memo of content hashes

    @property
    def stage(self) -> str:
        return self.record["stage"]

    @property
    def device(self) -> str:
        return self.run.get("device", "auto")

    @property
    def batch_size(self) -> int:
        return self.run.get("batch_size", 1)


def _images(job: Job) -> None:
    from vprflow.stages.dataset import build_images

    name = job.record["params"]["name"]
    build_images(name, job.record, job.data_root, job.out, job.fingerprints)


def _dataset(job: Job) -> None:
    from vprflow.stages.dataset import build_truth

    build_truth(job.inputs["images"], job.record, job.data_root, job.out, job.fingerprints)


def _features(job: Job) -> None:
    from vprflow.stages.features import compute_features

    compute_features(
        job.inputs["images"],
        job.record,
        job.out,
        job.data_root,
        job.device,
        job.batch_size,
        job.start,
        job.stop,
    )


def _segments(job: Job) -> None:
    from vprflow.stages.segments import compute_segments

    compute_segments(
        job.inputs["images"],
        job.record,
        job.out,
        job.data_root,
        job.device,
        job.batch_size,
        job.start,
        job.stop,
    )


def _vocabulary(job: Job) -> None:
    from vprflow.stages.vocabulary import fit_vocabulary

    fit_vocabulary(
        job.inputs["images"],
        job.inputs["features"],
        job.record,
        job.out,
        job.inputs.get("centres"),
    )


def _pca(job: Job) -> None:
    from vprflow.stages.pca import fit_pca_stage

    fit_pca_stage(job.inputs, job.record, job.out)


def _descriptors(job: Job) -> None:
    from vprflow.stages.descriptors import compute_descriptors

    compute_descriptors(job.inputs, job.record, job.out, job.start, job.stop, job.threads)


def _search(job: Job) -> None:
    from vprflow.stages.search import search_shard

    search_shard(
        job.inputs["images"],
        job.inputs["descriptors"],
        job.record,
        job.out,
        job.start,
        job.stop,
        job.device,
    )


def _recall(job: Job) -> None:
    from vprflow.stages.recall import evaluate

    evaluate(
        job.inputs["dataset"],
        job.inputs["descriptors"],
        job.record,
        job.out,
        search_path=job.inputs.get("search"),
        exact_search_path=job.inputs.get("exact_search"),
        rerank_path=job.inputs.get("rerank"),
    )


def _rerank(job: Job) -> None:
    from vprflow.stages.rerank import rerank_stage

    rerank_stage(job.inputs, job.record, job.out, job.device)


# Every stage the plan makes (vprflow.planning.plan.FORMAT_VERSIONS), by name. Stage modules
# are imported by the runner that needs them: importing torch or faiss costs seconds.
RUNNERS: dict[str, Callable[[Job], None]] = {
    "images": _images,
    "dataset": _dataset,
    "features": _features,
    "segments": _segments,
    "vocabulary": _vocabulary,
    "pca": _pca,
    "descriptors": _descriptors,
    "search": _search,
    "recall": _recall,
    "rerank": _rerank,
}

# Stages whose jobs each take a range of images, combined by `combine_shards`: the
# per-image stages, and the segment search (a range of reference images per job).
SHARDED = ("features", "segments", "descriptors", "search")


def run_job(job: Job) -> None:
    """Run one job of its stage (``job.record["stage"]``)."""
    RUNNERS[job.stage](job)


def shard_ranges(
    stage: str, n_reference: int, n_query: int, shard_size: int, search_shard_size: int
) -> list[tuple[int, int]]:
    """``(start, stop)`` image ranges of a sharded stage's jobs, in order: all images
    for a per-image stage (``shard_size`` each), the reference images for ``search``
    (``search_shard_size`` each); a size of 0 is one job."""
    if stage not in SHARDED:
        raise ValueError(f"stage {stage!r} is not sharded; sharded stages: {SHARDED}")
    if stage == "search":
        n_images, size = n_reference, search_shard_size
    else:
        n_images, size = n_reference + n_query, shard_size
    size = size or n_images
    return [(start, min(start + size, n_images)) for start in range(0, n_images, size)]


def combine_shards(shard_paths: list[str], record: dict, out: str) -> None:
    """One store from a sharded stage's shards (in order): search shards hold per-shard
    top-k lists and are merged; the others are concatenated."""
    from vprflow.stages.gather import gather
    from vprflow.stages.search import merge_search

    combine = merge_search if record["stage"] == "search" else gather
    combine(shard_paths, record, out)
