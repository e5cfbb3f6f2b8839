"""The report's tables (vprflow.stages.report): one row per method and every prediction."""

from __future__ import annotations

import csv

import pytest
from toy_pipeline import METHODS, N_PLACES, stage_path

from vprflow.core import stores
from vprflow.stages.report import write_predictions, write_recall_csv


def test_report_writes_one_row_per_method_and_every_prediction(pipeline, tmp_path):
    plan, _, recalls, _ = pipeline
    runs = [{"method": r.method, "params": r.row_params} for r in plan.runs["toy"]]
    csv_out, predictions_out = tmp_path / "recall.csv", tmp_path / "predictions.csv"
    dataset = stage_path(pipeline, "dataset")
    write_recall_csv("toy", runs, recalls, str(csv_out))
    write_predictions(dataset, runs, recalls, str(predictions_out))
    with open(csv_out) as f:
        rows = list(csv.DictReader(f))
    # Each method's row, its re-ranked rows right after it.
    rows_expected = [
        m
        for m in METHODS
        for m in (
            m,
            *{"anyloc_vlad": ["anyloc_vlad+mnn"], "segvlad": ["segvlad+ransac"]}.get(m, []),
        )
    ]
    assert [r["method"] for r in rows] == rows_expected
    for row, path in zip(rows, recalls, strict=True):
        attrs = stores.open_store(path).attrs
        assert float(row["recall@1"]) == pytest.approx(attrs["recall"]["1"], abs=1e-6)
        for name, value in attrs["precision_recall"].items():
            assert float(row[name]) == pytest.approx(value, abs=1e-6)
        assert (row["reranker"] != "") == ("+" in row["method"])
        assert (row["rerank_ms_per_query"] != "") == ("+" in row["method"])
    with open(predictions_out) as f:
        predictions = list(csv.DictReader(f))
    assert len(predictions) == len(rows_expected) * N_PLACES
    # Same inputs, same bytes.
    again = tmp_path / "again.csv"
    write_recall_csv("toy", runs, recalls, str(again))
    assert again.read_bytes() == csv_out.read_bytes()
