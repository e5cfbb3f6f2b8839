"""The figure rules: what the report shows of a dataset's results.

Each function reads the stores of one dataset (and one method) and writes one PNG with
:mod:`vprflow.evaluation.figures`. Figures are not stages: they hash nothing and change no key, so
a changed figure setting (``figures:`` in the config) reruns only figures. Images are
read with the project's reader from ``data_root``.
"""

from __future__ import annotations

import csv
import logging
from pathlib import Path

import numpy as np

from vprflow.aggregation.snsm import snsm_descriptor, snsm_grid_shape
from vprflow.core import stores
from vprflow.core.files import write_text_atomic
from vprflow.evaluation import figures
from vprflow.evaluation.precision_recall import precision_recall_curve
from vprflow.evaluation.recall import counted_queries
from vprflow.stages.readers import Dataset, FeatureReader, MaskReader
from vprflow.stages.retrieval import top1_matches

log = logging.getLogger("vprflow")


def _with_positives(dataset: Dataset) -> np.ndarray:
    """Queries with at least one positive (every query when there is no ground truth:
    then any query can be shown, none judged)."""
    if not dataset.has_ground_truth:
        return np.ones(dataset.n_query, dtype=bool)
    return np.array([len(t) > 0 for t in dataset.truth()], dtype=bool)


def plot_recall(
    dataset_name: str, dataset_path: str, methods: list[str], recall_paths: list[str], out: str
) -> None:
    """All methods' Recall@N for N = 1 .. the largest configured N, and beside them the
    precision-recall curves of their top-1 matches (the table's counting), on one figure."""

    dataset = Dataset(dataset_path)
    truth = dataset.truth()
    curves, precision_recall, marks, denominators = {}, {}, set(), set()
    for method, path in zip(methods, recall_paths, strict=True):
        result = stores.open_store(path)
        counted = counted_queries(truth, result.attrs["denominator"])
        denominators.add((result.attrs["denominator"], int(counted.sum())))
        recall_at = sorted(int(n) for n in result.attrs["recall"])
        marks.update(recall_at)
        n_max = min(max(recall_at), dataset.n_reference)
        curves[method] = figures.recall_curve(result["first_correct"][...], counted, n_max)
        ranking = np.asarray(result["ranking"][...])
        matches = top1_matches(
            ranking, result["scores"][...], result.attrs["score"], truth, counted
        )
        if matches is not None:
            precision_recall[method] = precision_recall_curve(*matches)[:2]
    over = ", ".join(f"{n} queries ({name})" for name, n in sorted(denominators))
    title = f"{dataset_name}: Recall@N over {over}, {dataset.group.attrs['ground_truth_rule']}"
    figure = figures.recall_curve_figure(curves, title, sorted(marks), precision_recall)
    figures.save_figure(figure, out)


def write_recall_table(dataset_name: str, csv_path: str, out: str) -> None:
    """The results table as an HTML page the report displays (the CSV is a download)."""
    with open(csv_path, newline="") as f:
        rows = list(csv.DictReader(f))
    rules = sorted({row["ground_truth"] for row in rows})
    counted = {
        "with_positives": "the queries with at least one positive (the others are left out)",
        "all": "all queries (one without a positive is a miss)",
    }
    denominators = sorted({row["denominator"] for row in rows})
    notes = [
        f"Positives by the ground-truth rule {', '.join(rules)}.",
        "Recall@N: the fraction of the counted queries whose first N retrieved references "
        "include a positive; mAP@N as Revisit-Anything computes it (docs/methods.md §8). "
        f"Counted: {'; '.join(counted[d] for d in denominators)}; n_queries says how many, "
        "n_queries_without_positive how many had no positive (the recall log names them). "
        "n_short_rankings: queries that ranked fewer references than the largest N "
        "(SegVLAD ranks only voted images); a missing rank is a miss.",
        "auc_pr, recall_at_100_precision, extended_precision: VPR-Bench's precision-recall "
        "summary of the top-1 matches over a threshold on their score (docs/methods.md §8; "
        "empty when no top-1 match is correct). A row named method+reranker re-orders that "
        "method's top K by local patch matches (§8).",
        "Cost: descriptor bytes an image adds to the database, and this run's milliseconds "
        "a query for the search and the re-ranking (they vary from run to run).",
        f"Every method parameter is a column of {Path(csv_path).name}.",
    ]
    title = f"{dataset_name}: Recall@N, mAP@N and top-1 precision-recall"
    write_text_atomic(out, figures.recall_table_html(rows, title, notes))


def sampled_queries(
    dataset: Dataset, first_correct: np.ndarray, settings: dict, count: int
) -> np.ndarray:
    """The queries a figure shows: ``count`` of those with a positive (only those wrong at
    rank 1 when ``settings["wrong_only"]``), chosen by ``settings["seed"]``."""
    candidates = np.flatnonzero(_with_positives(dataset))
    if settings["wrong_only"] and dataset.has_ground_truth:
        candidates = candidates[np.asarray(first_correct)[candidates] != 0]
    return figures.sample_queries(candidates, count, settings["seed"])


def draw_retrievals(
    inputs: dict[str, str], data_root: str, method: str, settings: dict, out: str
) -> None:
    """Sampled queries with their top ``settings["top"]`` references, framed green
    (a true positive) or red; ``inputs``: the ``dataset`` and ``recall`` stores."""
    dataset = Dataset(inputs["dataset"], data_root)
    result = stores.open_store(inputs["recall"])
    ranking = np.asarray(result["ranking"][...])
    first = np.asarray(result["first_correct"][...])
    truth, judged = dataset.truth(), dataset.has_ground_truth
    queries = sampled_queries(dataset, first, settings, settings["queries"])
    # A re-ranked method shows each query twice: re-ranked, then as retrieved.
    rankings = [("query", ranking)]
    if "retrieval_ranking" in result:
        retrieved = np.asarray(result["retrieval_ranking"][...])
        rankings = [("re-ranked", ranking), ("retrieved", retrieved)]
    rows = []
    for q in queries:
        for label, order in rankings:
            top = [int(r) for r in order[q, : settings["top"]] if r >= 0]
            rows.append(
                figures.RetrievalRow(
                    query=dataset.read_image(dataset.n_reference + q),
                    query_name=dataset.names[dataset.n_reference + q],
                    references=[dataset.read_image(r) for r in top],
                    reference_names=[dataset.names[r] for r in top],
                    correct=[bool(np.isin(r, truth[q])) if judged else None for r in top],
                    label=label,
                )
            )
    if not rows:
        log.warning("%s: no query to show (wrong_only and every query right at rank 1?)", method)
    what = "queries wrong at rank 1" if settings["wrong_only"] else "queries"
    title = f"{method}: {len(queries)} sampled {what} and their top {settings['top']} references"
    if len(rankings) > 1:
        title += ", re-ranked (upper row) and as retrieved (lower row)"
    figures.save_figure(figures.retrieval_figure(rows, title, settings["height"]), out)


def segment_matches(
    query_rows: range,
    indices: np.ndarray,
    reference_rows: range,
    descriptors,
) -> list[figures.SegmentMatch]:
    """For each query segment (global descriptor rows ``query_rows``), the nearest of its
    retrieved segments that lies in the reference image owning ``reference_rows``, and
    their cosine similarity. ``indices [len(query_rows), k]`` are the segment search's
    lists of these rows (global reference rows, nearest first, -1 padding); the
    returned segment numbers are local to the two images."""
    matches = []
    for i, row in enumerate(query_rows):
        inside = (indices[i] >= reference_rows.start) & (indices[i] < reference_rows.stop)
        hits = np.flatnonzero(inside)
        if len(hits) == 0:
            matches.append(figures.SegmentMatch(i, None, None))
            continue
        match = int(indices[i, hits[0]])
        q = np.asarray(descriptors[row], dtype=np.float64)
        r = np.asarray(descriptors[match], dtype=np.float64)
        cosine = float(q @ r / max(np.linalg.norm(q) * np.linalg.norm(r), 1e-12))
        matches.append(figures.SegmentMatch(i, match - reference_rows.start, cosine))
    return matches


def draw_segment_matches(
    inputs: dict[str, str], data_root: str, method: str, settings: dict, out: str
) -> None:
    """SegVLAD explanations: per sampled query, its segments beside its top-1 reference
    with each matched segment in the colour of the query segment that retrieved it.

    ``inputs``: the ``dataset``, ``recall``, ``search``, ``descriptors`` and ``segments``
    stores of the method.
    """

    dataset = Dataset(inputs["dataset"], data_root)
    result = stores.open_store(inputs["recall"])
    ranking = np.asarray(result["ranking"][...])
    first = np.asarray(result["first_correct"][...])
    group = stores.open_store(inputs["descriptors"])
    offsets = np.asarray(group["descriptors_offsets"][...])
    split = int(offsets[dataset.n_reference])
    search = stores.open_store(inputs["search"])
    masks = MaskReader(stores.open_store(inputs["segments"]))
    truth = dataset.truth()
    explanations = []
    for q in sampled_queries(dataset, first, settings, settings["explained_queries"]):
        image = dataset.n_reference + q
        top1 = int(ranking[q, 0])
        if top1 < 0:
            log.warning("%s: query %s ranked no reference", method, dataset.names[image])
            continue
        rows = range(int(offsets[image]), int(offsets[image + 1]))
        lists = slice(rows.start - split, rows.stop - split)
        matches = segment_matches(
            rows,
            np.asarray(search["indices"][lists]),
            range(int(offsets[top1]), int(offsets[top1 + 1])),
            group["descriptors"],
        )
        explanations.append(
            figures.SegmentExplanation(
                dataset.read_image(image),
                masks(image),
                dataset.read_image(top1),
                masks(top1),
                matches,
                f"{dataset.names[image]} -> {dataset.names[top1]}",
                bool(np.isin(top1, truth[q])) if dataset.has_ground_truth else None,
            )
        )
    if not explanations:
        raise ValueError(f"{method}: no sampled query ranked any reference to explain")
    title = f"{method}: which segments of the top-1 reference matched the query's"
    figures.save_figure(figures.segment_match_figure(explanations, title), out)


def draw_support_maps(
    inputs: dict[str, str], data_root: str, method: str, settings: dict, out: str
) -> None:
    """SNSM: sampled queries and their ground-truth references (for RoadScene, a thermal
    image and its RGB pair; without ground truth, their top-1 references) beside their
    support maps, computed with the method's own settings from the ``features`` store;
    ``inputs`` also has ``dataset``, ``recall`` and ``descriptors`` (whose attributes
    hold those settings)."""

    dataset = Dataset(inputs["dataset"], data_root)
    result = stores.open_store(inputs["recall"])
    first = np.asarray(result["first_correct"][...])
    top1 = np.asarray(result["ranking"][:, 0])
    options = stores.open_store(inputs["descriptors"]).attrs["record"]["params"]
    keys = ("upscale", "window", "neighbourhood", "similarity", "normalization")
    snsm = {k: options[k] for k in keys}
    features = stores.open_store(inputs["features"])
    read_features = FeatureReader(features, block_bytes=0)
    turn = features.attrs["record"]["params"]["exif_orientation"]  # the pixels SNSM saw
    truth = dataset.truth()

    def support(index: int) -> np.ndarray:
        tokens = read_features(index)
        shape = snsm_grid_shape(tokens.shape[0], tokens.shape[1], snsm["upscale"], snsm["window"])
        return snsm_descriptor(tokens, **snsm).reshape(shape)

    rows = []
    for q in sampled_queries(dataset, first, settings, settings["explained_queries"]):
        reference = int(truth[q][0]) if dataset.has_ground_truth else int(top1[q])
        image = dataset.n_reference + q
        rows.append(
            (
                dataset.names[image],
                dataset.read_image(image, turn),
                support(image),
                dataset.names[reference],
                dataset.read_image(reference, turn),
                support(reference),
            )
        )
    which = "true" if dataset.has_ground_truth else "top-1"
    title = f"{method}: support maps of sampled queries and their {which} references"
    figures.save_figure(figures.support_map_figure(rows, title), out)


# Each figure of vprflow.planning.reports.FIGURES by name, and the function that draws it.
DRAW = {
    "retrievals": draw_retrievals,
    "segment_matches": draw_segment_matches,
    "support_maps": draw_support_maps,
}


def draw_figure(
    figure: str, inputs: dict[str, str], data_root: str, method: str, settings: dict, out: str
) -> None:
    """Draw one method's ``figure`` (a name in :data:`vprflow.planning.reports.FIGURES`) with
    its function in :data:`DRAW`: a figure rule passes the figure's name, never its rule
    name, which a host workflow may prefix."""
    if figure not in DRAW:
        raise ValueError(f"unknown figure {figure!r}; figures: {sorted(DRAW)}")
    DRAW[figure](inputs, data_root, method, settings, out)
