"""The README's numbers that a run decides stay the run's: corridor's SegVLAD Recall@1
with the shipped PCA and with the published one. ``benchmarks/bench_readme.py`` owns
every number the README quotes (it also times the install and the corridor run, which
no test may); this reads the test suite's own corridor run."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
from workflow_helpers import SCHEMA, built_stores, repo_config, write_table

from vprflow.planning.config import validate_config
from vprflow.planning.plan import build_plan

REPO = Path(__file__).resolve().parents[2]


def bench_readme():
    path = REPO / "benchmarks" / "bench_readme.py"
    spec = importlib.util.spec_from_file_location("bench_readme", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.workflow
@pytest.mark.data
def test_the_readmes_segvlad_recall_at_1_values_are_the_corridor_runs(
    corridor_run, data_root, tmp_path
):
    bench = bench_readme()
    quoted = bench.readme_quotes((REPO / "README.md").read_text())
    source, _ = corridor_run
    shipped = bench.recall_at_1(source / "results" / "recall_corridor.csv", "segvlad")
    # Only SegVLAD's PCA and what follows it are new: computed in this process beside the
    # shared run's stores, which it reads and leaves as they are.
    config = repo_config()
    config["data_root"] = str(data_root)
    plan = build_plan(validate_config(bench.published_pca_config(config), SCHEMA))
    table = write_table(plan, "corridor", data_root, tmp_path, built_stores(plan, source))
    published = bench.recall_at_1(table, "segvlad")
    measured = {"segvlad_r1_shipped_pca": shipped, "segvlad_r1_published_pca": published}
    for name, value in measured.items():
        assert quoted[name] == (round(value, 2),), f"README.md: {name} {quoted[name]}, run {value}"


def test_the_published_pca_comparison_changes_only_segvlads_pca_and_rows():
    """What README.md calls the published PCA (1024 whitened components) over the shipped
    corridor entry, SegVLAD alone; every other key as shipped."""
    config = repo_config()
    corridor = bench_readme().published_pca_config(config)["datasets"]["corridor"]
    assert corridor["defaults"] == {"pca": {"dim": 1024, "whiten": True}}
    assert corridor["methods"] == ["segvlad"] and corridor["rerank"] == {"segvlad": []}
    changed = ("defaults", "methods", "rerank")
    shipped = config["datasets"]["corridor"]
    assert shipped["defaults"]["pca"] != corridor["defaults"]["pca"]
    assert {k: v for k, v in corridor.items() if k not in changed} == {
        k: v for k, v in shipped.items() if k not in changed
    }
