"""The shipped config on the real datasets under $VPRFLOW_DATA: corridor's whole DAG
through Snakemake, roadscene's tables (conftest.py)."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest
from workflow_helpers import expected_rows, repo_config, scheduled_files, write_config

pytestmark = [pytest.mark.workflow, pytest.mark.data]


def table(workdir: Path, dataset: str) -> dict[str, dict]:
    """The dataset's recall table by method, its rows checked to be the config's."""
    with open(workdir / f"results/recall_{dataset}.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["method"] for r in rows] == expected_rows(repo_config()["datasets"][dataset])
    return {r["method"]: r for r in rows}


def figures(dataset: str, rows: dict[str, dict]) -> list[str]:
    """The recall plot and every method's figures."""
    expected = [f"results/plots/recall_{dataset}.png"]
    for method, row in rows.items():
        expected.append(f"results/figures/{dataset}/retrievals/{method}.png")
        explanation = {"segvlad": "segment_matches", "snsm": "support_maps"}
        # A re-ranked row's explanation is its method's row's.
        if row["aggregator"] in explanation and not row.get("reranker"):
            figure = explanation[row["aggregator"]]
            expected.append(f"results/figures/{dataset}/{figure}/{method}.png")
    return expected


def assert_figures_drawn(workdir: Path, dataset: str, rows: dict[str, dict]) -> None:
    """The recall plot and every method's figures exist as PNG files."""
    from PIL import Image

    for path in figures(dataset, rows):
        with Image.open(workdir / path) as image:
            assert image.format == "PNG", path


def test_corridor_recall_is_well_above_chance(corridor_run):
    workdir, _ = corridor_run
    rows = table(workdir, "corridor")
    assert_figures_drawn(workdir, "corridor", rows)
    # 111 references, about 5 positives per query: chance Recall@1 is about 0.045.
    for method, row in rows.items():
        assert row["n_queries"] == "111" and row["ground_truth"] == "vprbench:ground_truth_new.npy"
        assert float(row["recall@1"]) > 0.1, method
        assert float(row["recall@20"]) > 0.5, method
    for method in ("anyloc_vlad", "segvlad_nopca", "segvlad_o0_nopca"):
        assert float(rows[method]["recall@1"]) > 0.5, method


def test_roadscene_rgb_thermal_methods_beat_chance(roadscene_run, data_root, tmp_path):
    rows = table(roadscene_run, "roadscene")
    # Its table is computed in-process (conftest.py); `snakemake` plans its figures too.
    config = repo_config() | {"data_root": str(data_root), "targets": ["roadscene"]}
    scheduled = scheduled_files(tmp_path, write_config(tmp_path, config), "all")
    assert set(figures("roadscene", rows)) <= scheduled
    # 50 pairs, one positive each: chance Recall@1 is 0.02, Recall@10 0.2.
    for method, row in rows.items():
        assert row["n_queries"] == "50" and row["ground_truth"] == "pairs"
        # Every reference is ranked, so @50 finds every pair, unless the method ranks
        # only some images (SegVLAD's published voting) and says so.
        if row["n_short_rankings"] == "0":
            assert float(row["recall@50"]) == 1.0, method
        else:
            assert row["aggregator"] == "segvlad", method
    for method in ("snsm", "snsm_neg_l2", "anyloc_vlad", "anyloc_vlad_thermal"):
        assert float(rows[method]["recall@1"]) >= 0.15, method
        assert float(rows[method]["recall@10"]) >= 0.5, method
    # The published finding on aligned RGB-thermal pairs: support maps beat plain pooling.
    pooled = max(float(rows[m]["recall@5"]) for m in ("gem", "average", "max"))
    assert float(rows["snsm"]["recall@5"]) > pooled
    assert rows["snsm"]["snsm.neighbourhood"] == "diagonal4"
    assert rows["anyloc_vlad_thermal"]["vocabulary.fit_on"] == "query"
