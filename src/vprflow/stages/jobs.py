"""How the rules' script, the tests and the benchmarks run a job of any stage.

A rule hands its script a :class:`Job` (the stage's hashed record, its input stores,
its output, and how to run); :func:`run_job` calls the function that
:data:`vprflow.planning.plan.STAGES` names for ``record["stage"]``, with the job.
The sharding policy comes from the same table: which stages run in shards, over which
image ranges (:func:`shard_ranges`), and how shards become one store
(:func:`combine_shards`).
"""

from __future__ import annotations

import json
from pathlib import Path

from vprflow.core.registry import resolve
from vprflow.planning.plan import SHARDED, STAGES
from vprflow.stages.base import Job

__all__ = [
    "RUNNERS",
    "SHARDED",
    "Job",
    "built_shard_ranges",
    "combine_shards",
    "run_job",
    "shard_ranges",
]

# Every stage's runner, as "module:function" (the table's column): imported by the job
# that runs it, since importing torch or faiss costs seconds.
RUNNERS: dict[str, str] = {name: stage.runner for name, stage in STAGES.items()}


def run_job(job: Job) -> None:
    """Run one job of its stage (``job.record["stage"]``)."""
    resolve(RUNNERS[job.stage])(job)


def shard_ranges(
    stage: str, n_reference: int, n_query: int, shard_size: int, search_shard_size: int
) -> list[tuple[int, int]]:
    """``(start, stop)`` image ranges of a sharded stage's jobs, in order: all images
    for a stage sharded over images (``shard_size`` each), the reference images for one
    sharded over references (``search_shard_size`` each); a size of 0 is one job."""
    if stage not in SHARDED:
        raise ValueError(f"stage {stage!r} is not sharded; sharded stages: {SHARDED}")
    if STAGES[stage].shards == "references":
        n_images, size = n_reference, search_shard_size
    else:
        n_images, size = n_reference + n_query, shard_size
    size = size or n_images
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
    """One store from a sharded stage's shards (in order), as the table's ``combine``
    says: search shards hold per-shard top-k lists and are merged; the others are
    concatenated."""
    resolve(STAGES[record["stage"]].combine)(shard_paths, record, out)
