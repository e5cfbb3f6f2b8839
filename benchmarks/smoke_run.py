"""The one Snakemake run that the smoke modes of bench_city.py, bench_workflow.py,
bench_fixed_cost.py and bench_descriptors.py share where ``$VPRFLOW_SMOKE_RUN`` names a
folder holding it: each of them would otherwise make its own run of the same ~20 jobs,
~12 CPU seconds each. Without the variable, or before the run is there, each script
makes its own, as documented.

``python benchmarks/bench_city.py --make-smoke-run FOLDER`` makes it (bench_city.py's
smoke city through the shipped config's corridor entry with segvlad re-ranked by mnn,
the shipped shard settings, one core, bench_fixed_cost.py's job recorder);
tests/repository/test_benchmarks.py makes it once for all its workers and sets the
variable. This module only reads it, so the scripts that read it import nothing of the
one that makes it. Not a ``bench_*`` script: the benchmarks import it.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

VARIABLE = "VPRFLOW_SMOKE_RUN"
TARGET = "results/recall_city.csv"
# Written last, once the run is whole: a folder without it holds no run to read.
RECORD = "run.json"


def shared_run() -> tuple[Path, dict] | None:
    """The shared run's work folder and its ``run.json`` (images, cores, shard settings,
    seconds to generate the images, wall seconds of the run); None where
    ``$VPRFLOW_SMOKE_RUN`` is unset or holds no finished run."""
    root = os.environ.get(VARIABLE)
    record = Path(root) / RECORD if root else None
    if record is None or not record.is_file():
        return None
    return Path(root) / "run", json.loads(record.read_text())
