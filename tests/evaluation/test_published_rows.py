"""results/published_<dataset>.csv (vprflow.evaluation.published_rows): each published
row of a preset beside the recall of the vprflow method it names, without Snakemake."""

from __future__ import annotations

import csv

import pytest

from vprflow.core.paths import PUBLISHED_CSV
from vprflow.data.presets import presets
from vprflow.evaluation.published_rows import COLUMNS, published_rows, write_published_table


def recall_csv(path, rows: list[dict[str, str]]) -> str:
    """A recall table with the columns the published table reads (and one it ignores)."""
    with open(path, "w", newline="") as f:
        columns = ["dataset", "method", "recall@1", "recall@5", "n_queries", "protocol"]
        writer = csv.DictWriter(f, fieldnames=columns)
        writer.writeheader()
        writer.writerows(rows)
    return str(path)


TABLE = [
    # segvlad+mnn shares segvlad's prefix: only the exact method's row is read.
    {"method": "segvlad+mnn", "recall@1": "0.999999", "recall@5": "1.000000"},
    {"method": "anyloc_vlad", "recall@1": "0.876543", "recall@5": "0.947000"},
    {"method": "segvlad", "recall@1": "0.120000", "recall@5": "0.333333"},
    {"method": "mixvpr", "recall@1": "0.916000", "recall@5": "0.955000"},
]


def test_each_published_row_gets_its_methods_recall_in_percent_in_the_presets_order(tmp_path):
    same = {"dataset": "pitts30k", "n_queries": "4", "protocol": "preset pitts30k"}
    rows = [{**same, **r} for r in TABLE]
    out = tmp_path / "results" / "published_pitts30k.csv"
    write_published_table("pitts30k", recall_csv(tmp_path / "recall.csv", rows), str(out))
    assert str(out).endswith(PUBLISHED_CSV.format(dataset="pitts30k"))
    with open(out, newline="") as f:
        table = list(csv.DictReader(f))
    published = presets()["pitts30k"].published
    assert tuple(table[0]) == COLUMNS
    assert [r["method"] for r in table] == [p["method"] for p in published]
    by_method = {r["method"]: r for r in TABLE}
    for row, entry in zip(table, published, strict=True):
        assert row["paper"] == entry["paper"]
        assert float(row["published_recall@1"]) == entry["recall@1"]
        assert float(row["published_recall@5"]) == entry["recall@5"]
        ours = by_method.get(entry.get("row"))
        if ours is None:  # no vprflow method, or none in this table (convap, boq_*)
            assert row["recall@1"] == row["recall@5"] == row["protocol"] == ""
            continue
        # float64 percent of the table's fraction, to the two decimals written.
        for n in (1, 5):
            expected = 100.0 * float(ours[f"recall@{n}"])
            assert abs(float(row[f"recall@{n}"]) - expected) <= 0.005 + 1e-12
        assert row["protocol"] == "preset pitts30k"
    rows = {r["row"]: r for r in table if r["row"]}
    assert rows["anyloc_vlad"]["recall@1"] == "87.65" and rows["segvlad"]["recall@5"] == "33.33"
    assert rows["mixvpr"]["recall@1"] == "91.60" and rows["convap"]["recall@1"] == ""
    fine_tuned = next(r for r in table if r["method"] == "SegVLAD-FineT (M)")
    assert fine_tuned["row"] == "" and fine_tuned["recall@1"] == ""
    assert not list(out.parent.glob(".*.tmp"))  # written whole


def test_a_changed_protocol_reaches_the_published_table():
    changed = "preset pitts30k, changed: ground_truth.radius"
    rows = published_rows(
        [{"method": "A", "paper": "P", "recall@1": 1.5, "recall@5": 2, "row": "anyloc_vlad"}],
        [{**TABLE[1], "protocol": changed}],
    )
    assert rows == [
        {
            "method": "A",
            "paper": "P",
            "published_recall@1": "1.5",
            "published_recall@5": "2",
            "row": "anyloc_vlad",
            "recall@1": "87.65",
            "recall@5": "94.70",
            "protocol": changed,
        }
    ]


def test_a_dataset_that_is_no_preset_is_named(tmp_path):
    path = recall_csv(tmp_path / "recall.csv", [])
    with pytest.raises(ValueError, match="'corridor' is not a vprflow preset"):
        write_published_table("corridor", path, str(tmp_path / "out.csv"))
    assert not (tmp_path / "out.csv").exists()
