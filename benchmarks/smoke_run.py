"""The one Snakemake run that the smoke modes of bench_city.py, bench_workflow.py,
bench_fixed_cost.py and bench_descriptors.py share where ``$VPRFLOW_SMOKE_RUN`` names a
folder (tests/repository/test_benchmarks.py sets it): each of them started its own run of the same
~20 jobs, ~12 CPU seconds each. Without the variable, each script makes its own run, as
documented.

The run: bench_city.py's smoke city (:data:`bench_city.SMOKE_IMAGES` images in the
pitts30k layout, at the corridor entry's resolution) through the shipped config's
corridor entry with segvlad re-ranked by mnn (bench_workflow.SMOKE_METHODS: its DAG holds
every stage, and every input of anyloc_vlad's descriptors, which bench_descriptors.py
times too) and the shipped shard settings, on one core with bench_fixed_cost.py's job
recorder. The first script to ask makes it, under a lock; the others wait for it and
read it. A failed run leaves no ``run.json``, so the next to ask runs it again (and fails
with its own output). Not a ``bench_*`` script: the benchmarks import it.
"""

from __future__ import annotations

import fcntl
import json
import os
import shutil
import time
from pathlib import Path

import yaml

VARIABLE = "VPRFLOW_SMOKE_RUN"
TARGET = "results/recall_city.csv"


def shared_run(data: Path) -> tuple[Path, dict] | None:
    """The finished shared run's work folder and its ``run.json`` (images, cores, shard
    settings, seconds to generate the images, wall seconds of the run), made now if no
    script has made it yet; None where ``$VPRFLOW_SMOKE_RUN`` is unset."""
    root = os.environ.get(VARIABLE)
    if not root:
        return None
    root = Path(root)
    folder, record = root / "run", root / "run.json"
    root.mkdir(parents=True, exist_ok=True)
    with open(root / "lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes, or the process ends
        if not record.is_file():
            from bench_city import REPO, SMOKE_IMAGES, city_config, make_city
            from bench_fixed_cost import CORES, recorded_run
            from bench_workflow import SMOKE_METHODS, SMOKE_RERANK

            shutil.rmtree(folder, ignore_errors=True)
            config = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
            size = tuple(config["datasets"]["corridor"]["resolution"])
            start = time.perf_counter()
            city = make_city(data, root / "data", SMOKE_IMAGES, size)
            generate = time.perf_counter() - start
            config_path = city_config(folder, city, SMOKE_METHODS, SMOKE_RERANK)
            start = time.perf_counter()
            recorded_run(folder, config_path, TARGET)
            shards = f"shard {config['shard_size']}, descriptors {config['descriptors_shard_size']}"
            run = {"images": SMOKE_IMAGES, "cores": CORES, "shards": shards}
            run |= {"generate_s": generate, "wall": time.perf_counter() - start}
            partial = record.with_suffix(".tmp")
            partial.write_text(json.dumps(run))
            os.replace(partial, record)
    return folder, json.loads(record.read_text())
