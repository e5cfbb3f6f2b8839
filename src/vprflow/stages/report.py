"""The ``recall_csv`` and ``predictions`` rules: a dataset's results table and its
per-query top references with scores."""

from __future__ import annotations

import csv

import numpy as np

from vprflow.core import stores
from vprflow.core.files import atomic_path
from vprflow.evaluation.precision_recall import SUMMARY
from vprflow.evaluation.recall import COST_COLUMNS
from vprflow.stages.readers import Dataset

# The precision-recall summary of the top-1 matches and what a query costs (descriptor
# bytes are exact; milliseconds are this run's, not a result).


def write_recall_csv(
    dataset_name: str, runs: list[dict], recall_paths: list[str], csv_out: str
) -> None:
    """The results table: one row per method (``runs[i]`` is ``{"method": name,
    "params": {flattened parameters}}`` for ``recall_paths[i]``), with Recall@N, mAP@N,
    the precision-recall summary and the cost per query. Fixed column order, no
    timestamps; only the milliseconds vary from one build of a recall store to the next."""
    results = [stores.open_store(p) for p in recall_paths]
    if any(r.attrs["ground_truth_rule"] == "none" for r in results):
        raise ValueError(
            f"dataset {dataset_name!r} has no ground truth (kind: none): there is no recall "
            f"to tabulate; its rankings are in results/predictions_{dataset_name}.csv"
        )
    recall_columns = sorted({int(n) for r in results for n in r.attrs["recall"]})
    param_columns = sorted({name for run in runs for name in run["params"]})
    # The results lead (what a reader compares), then what was counted and how, then
    # every parameter that shaped the row.
    header = ["dataset", "method"]
    header += [f"recall@{n}" for n in recall_columns]
    header += [f"map@{n}" for n in recall_columns]
    header += [*SUMMARY]
    # Rows of an approximate segment search also show an exact search's recall.
    exact = [r.attrs.get("recall_exact") or {} for r in results]
    if any(exact):
        header += [f"exact_recall@{n}" for n in recall_columns]
    header += ["n_queries", "n_short_rankings", "n_queries_without_positive"]
    header += ["ground_truth", "denominator", "descriptor_dim", *COST_COLUMNS, *param_columns]
    rows = []
    for run, result, exact_recall in zip(runs, results, exact, strict=True):
        attrs = result.attrs
        rows.append(
            [dataset_name, run["method"]]
            + _metric_cells(attrs["recall"], recall_columns)
            + _metric_cells(attrs["map"], recall_columns)
            + [_number(attrs["precision_recall"].get(c), ".6f") for c in SUMMARY]
            + (_metric_cells(exact_recall, recall_columns) if any(exact) else [])
            + [attrs["n_queries"], attrs["n_short_rankings"], attrs["n_queries_without_positive"]]
            + [attrs["ground_truth_rule"], attrs["denominator"], attrs["descriptor_dim"]]
            # Bytes whole (a per-segment method's are a mean over images), ms to 3 digits.
            + [
                _number(attrs["cost"].get(c), ".0f" if "bytes" in c else ".3g")
                for c in COST_COLUMNS
            ]
            + [_cell(run["params"].get(name, "")) for name in param_columns]
        )
    _write_csv(csv_out, header, rows)


def write_predictions(
    dataset_path: str, runs: list[dict], recall_paths: list[str], predictions_out: str
) -> None:
    """Per method and query: its image, its positives (none without ground truth), the
    rank of the first correct reference, and the top references with their scores
    (squared L2 distance for global descriptors, lower is better; SegVLAD's votes,
    higher is better: ``score_kind`` says which)."""
    dataset = Dataset(dataset_path)
    truth = dataset.truth()
    header = ["method", "query", "query_image", "positives", "first_correct_rank"]
    header += ["top", "top_images", "score_kind", "top_scores"]
    rows = []
    for run, path in zip(runs, recall_paths, strict=True):
        result = stores.open_store(path)
        ranking = np.asarray(result["ranking"][...])
        scores = np.asarray(result["scores"][...])
        first = np.asarray(result["first_correct"][...])
        for q in range(dataset.n_query):
            kept = ranking[q] >= 0
            top = ranking[q][kept]
            rows.append(
                [
                    run["method"],
                    q,
                    dataset.names[dataset.n_reference + q],
                    " ".join(map(str, truth[q])),
                    int(first[q]) + 1 if first[q] >= 0 else "",
                    " ".join(map(str, top)),
                    " ".join(dataset.names[r] for r in top),
                    result.attrs["score"],
                    " ".join(f"{v:.6g}" for v in scores[q][kept]),
                ]
            )
    _write_csv(predictions_out, header, rows)


def _write_csv(path: str, header: list[str], rows: list[list]) -> None:
    """Write via a temporary file, so an interrupted job leaves no complete-looking table."""
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(header)
        writer.writerows(rows)


def _metric_cells(values: dict, columns: list[int]) -> list[str]:
    return [f"{values[str(n)]:.6f}" if str(n) in values else "" for n in columns]


def _number(value, spec: str) -> str:
    return "" if value is None else format(value, spec)


def _cell(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return str(value)
