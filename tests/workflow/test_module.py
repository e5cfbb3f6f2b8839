"""vprflow imported as a Snakemake module by a host workflow, with a prefix and renamed
rules, running the .test config (the corridor images) to vprflow's default target: tables,
recall plot and figures."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

pytestmark = [pytest.mark.workflow, pytest.mark.data]

REPO = Path(__file__).resolve().parents[2]

HOST = """\
configfile: "config.yaml"


module vprflow:
    snakefile:
        "{snakefile}"
    config:
        config
    prefix:
        "vpr"


use rule * from vprflow as vpr_*


# vprflow's own default target (its `all`, imported as vpr_all): tables and figures.
rule all:
    default_target: True
    input:
        rules.vpr_all.input,
"""


def test_host_workflow_runs_vprflow_as_a_prefixed_module(tmp_path, data_root):
    config = yaml.safe_load((REPO / ".test" / "config" / "config.yaml").read_text())
    config["data_root"] = str(data_root)
    (tmp_path / "config.yaml").write_text(yaml.safe_dump(config))
    (tmp_path / "Snakefile").write_text(HOST.format(snakefile=REPO / "workflow" / "Snakefile"))
    command = [sys.executable, "-m", "snakemake", "--cores", "2"]
    result = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-5000:]
    # vprflow's default target, figures included, drawn by rules named vpr_*.
    methods = config["datasets"]["corridor"]["methods"]
    shown = [
        "results/plots/recall_corridor.png",
        "results/tables/recall_corridor.html",
        *(f"results/figures/corridor/retrievals/{method}.png" for method in methods),
        "results/figures/corridor/segment_matches/segvlad.png",
    ]
    assert [p for p in shown if not (tmp_path / "vpr" / p).is_file()] == []
    with open(tmp_path / "vpr" / "results" / "recall_corridor.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["method"] for r in rows] == methods
    for row in rows:
        assert row["n_queries"] == "111"
        assert 0.1 < float(row["recall@10"]) <= 1.0, row["method"]
    # Everything the module writes is under its prefix: stores, index, logs.
    assert (tmp_path / "vpr" / "results" / "cache" / "index.tsv").exists()
    assert list((tmp_path / "vpr" / "logs" / "recall").glob("*/*.log"))
    assert not (tmp_path / "results").exists()
    # A second run finds nothing to do.
    again = subprocess.run([*command, "-n"], cwd=tmp_path, capture_output=True, text=True)
    assert "Nothing to be done" in again.stdout + again.stderr
