"""The ``report`` rule: a dataset's results table and per-query predictions."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vprflow import stores
from vprflow.stages.dataset import Dataset


def write_report(
    dataset_name: str,
    dataset_path: str,
    runs: list[dict],
    recall_paths: list[str],
    csv_out: str,
    predictions_out: str,
) -> None:
    """The results table (one row per method) and per-query top predictions.

    ``runs[i]`` is ``{"method": name, "params": {flattened parameters}}`` for
    ``recall_paths[i]``. Output is deterministic: fixed column order, no timestamps.
    """
    import csv

    dataset = Dataset(dataset_path)
    results = [stores.open_store(p) for p in recall_paths]
    recall_columns = sorted({int(n) for r in results for n in r.attrs["recall"]})
    param_columns = sorted({name for run in runs for name in run["params"]})
    header = ["dataset", "method", *param_columns, "descriptor_dim", "ground_truth"]
    header += ["n_queries", "n_short_rankings"]
    header += [f"recall@{n}" for n in recall_columns]
    # Rows of an approximate segment search also show an exact search's recall.
    exact = [r.attrs.get("recall_exact") or {} for r in results]
    if any(exact):
        header += [f"exact_recall@{n}" for n in recall_columns]
    Path(csv_out).parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(csv_out).with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(header)
        for run, result, exact_recall in zip(runs, results, exact, strict=True):
            recall = result.attrs["recall"]
            writer.writerow(
                [dataset_name, run["method"]]
                + [_cell(run["params"].get(name, "")) for name in param_columns]
                + [result.attrs["descriptor_dim"], result.attrs["ground_truth_rule"]]
                + [result.attrs["n_queries"], result.attrs["n_short_rankings"]]
                + _recall_cells(recall, recall_columns)
                + (_recall_cells(exact_recall, recall_columns) if any(exact) else [])
            )
    tmp.replace(csv_out)
    tmp = Path(predictions_out).with_suffix(".csv.tmp")
    truth = dataset.truth()
    with open(tmp, "w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(
            ["method", "query", "query_image", "positives", "first_correct_rank", "top"]
        )
        for run, result in zip(runs, results, strict=True):
            ranking = np.asarray(result["ranking"][...])
            first = np.asarray(result["first_correct"][...])
            for q in range(dataset.n_query):
                writer.writerow(
                    [
                        run["method"],
                        q,
                        dataset.names[dataset.n_reference + q],
                        " ".join(map(str, truth[q])),
                        int(first[q]) + 1 if first[q] >= 0 else "",
                        " ".join(map(str, ranking[q][ranking[q] >= 0])),
                    ]
                )
    tmp.replace(predictions_out)


def _recall_cells(recall: dict, columns: list[int]) -> list[str]:
    return [f"{recall[str(n)]:.6f}" if str(n) in recall else "" for n in columns]


def _cell(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)
