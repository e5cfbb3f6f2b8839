"""What vprflow hands to other tools: the ``export`` rule writes one method's
descriptors of a dataset in a single ``.npz`` file; the ``pairs`` rule writes one
method's (or re-ranked row's) retrievals as the pairs files localisation pipelines read.

The file holds plain arrays (read with ``np.load(path)``, no pickle):

- ``names [n]`` image paths relative to the dataset folder, references first;
- ``is_query [n]`` bool;
- ``descriptors``: ``[n, dim]`` for global methods, or ``[S, dim]`` for per-segment
  ones (SegVLAD), whose segments of image ``i`` are rows
  ``offsets[i]:offsets[i + 1]`` (``offsets [n + 1]``);
- ``kind``: ``"global"`` or ``"segments"``; ``method``, ``dataset``.

For data too large for one file, read the Zarr store itself (README: "Reading the
stores").
"""

from __future__ import annotations

import numpy as np

from vprflow.core import stores
from vprflow.core.files import atomic_path
from vprflow.stages.readers import Dataset
from vprflow.stages.retrieval import retrieve


def export_descriptors(
    dataset_name: str, method: str, dataset_path: str, descriptors_path: str, out: str
) -> None:
    """Write ``out`` (an ``.npz``) from the images and descriptors stores."""
    dataset = Dataset(dataset_path)
    group = stores.open_store(descriptors_path)
    arrays = {
        "names": np.array(dataset.names),
        "is_query": np.arange(dataset.n_images) >= dataset.n_reference,
        "descriptors": np.asarray(group["descriptors"][...]),
        "kind": np.array(group.attrs["kind"]),
        "method": np.array(method),
        "dataset": np.array(dataset_name),
    }
    if group.attrs["kind"] == "segments":
        arrays["offsets"] = np.asarray(group["descriptors_offsets"][...])
    with atomic_path(out, suffix=".npz") as tmp:  # np.savez appends .npz otherwise
        np.savez(tmp, **arrays)


# kapture's pairs file (kapture format 1.0, as SNSM's All-Backbones-VLAD_bl.py writes its
# predictions.txt): comment lines, then `query_image, map_image, score` per line.
KAPTURE_HEADER = "# kapture format: 1.0\n# query_image, map_image, score\n"
SCORE_MEANING = {
    "squared_l2": "squared L2 distance of the descriptors, lower is better",
    "votes": "SegVLAD's image votes, higher is better",
}


def ranking_at_depth(
    dataset: Dataset,
    recall_path: str,
    depth: int,
    descriptors_path: str,
    search_path: str | None = None,
) -> tuple[np.ndarray, np.ndarray, str]:
    """Each query's first ``depth`` references (at most every reference), ``(ranking
    [Nq, depth'] int64, scores, score kind)``, ``-1`` where a ranking ends early.

    The recall store's ranking (what its table scored: as deep as the recall's depth, at
    least the deepest Recall@N, and a re-ranked row's as deep as its re-ranker's top K) is cut to
    ``depth``; a deeper ``depth`` continues it with the method's own retrieval
    (:func:`vprflow.stages.retrieval.retrieve` over the descriptors and search stores),
    skipping references already ranked, so no stage reruns for it. Continued entries of a
    re-ranked row score as its lowest score (0 when none), as the re-ranking scores the
    retrieval's entries past its top K. A per-segment method ranks only images that got a
    vote (``vote_ranking: published``): its rows may end before ``depth``."""

    result = stores.open_store(recall_path)
    ranking = np.asarray(result["ranking"][...])
    scores = np.asarray(result["scores"][...], dtype=np.float64)
    kind = result.attrs["score"]
    depth = min(depth, dataset.n_reference)
    if depth <= ranking.shape[1]:
        return ranking[:, :depth], scores[:, :depth], kind
    params = result.attrs["record"]["params"]
    more, more_scores, more_kind = retrieve(
        dataset, descriptors_path, depth, search_path, params.get("vote_ranking")
    )
    deep = np.full((len(ranking), depth), -1, dtype=np.int64)
    deep_scores = np.zeros(deep.shape)
    for q, (row, row_scores) in enumerate(zip(ranking, scores, strict=True)):
        kept = row >= 0
        row, row_scores = row[kept], row_scores[kept]
        new = (more[q] >= 0) & ~np.isin(more[q], row)
        if more_kind == kind:
            extra_scores = np.asarray(more_scores[q], dtype=np.float64)[new]
        else:
            extra_scores = np.full(int(new.sum()), row_scores.min() if len(row_scores) else 0.0)
        joined = np.concatenate([row, more[q][new]])[:depth]
        deep[q, : len(joined)] = joined
        deep_scores[q, : len(joined)] = np.concatenate([row_scores, extra_scores])[: len(joined)]
    return deep, deep_scores, kind


def write_pairs(
    dataset_path: str,
    recall_path: str,
    pairs_out: str,
    kapture_out: str,
    depth: int,
    descriptors_path: str,
    search_path: str | None = None,
) -> None:
    """Each query's first ``depth`` ranked references (:func:`ranking_at_depth`; a short
    ranking ends early), in the order the recall stage scored them, as:

    - ``pairs_out``: ``query reference`` per line (hloc's retrieval pairs,
      ``pairs_from_retrieval``), best first;
    - ``kapture_out``: kapture's pairs file, ``query, reference, score`` per line, the
      score as stored (a comment line says which kind).

    Names are image paths relative to the dataset folder (hloc's and kapture's image
    names when their image root is that folder)."""
    dataset = Dataset(dataset_path)
    ranking, scores, kind = ranking_at_depth(
        dataset, recall_path, depth, descriptors_path, search_path
    )
    names = dataset.names
    # Both formats split lines on their separators: a name holding one cannot be written.
    for name in names:
        if any(c.isspace() for c in name) or "," in name:
            raise ValueError(
                f"image {name!r} has a space or comma in its name: hloc's pairs file "
                "separates names by spaces and kapture's by commas; rename it to export pairs"
            )
    pairs, kapture = [], [KAPTURE_HEADER, f"# score: {SCORE_MEANING.get(kind, kind)}\n"]
    for q in range(dataset.n_query):
        query = names[dataset.n_reference + q]
        for r, score in zip(ranking[q], scores[q], strict=True):
            if r < 0:  # a short ranking (SegVLAD ranks only voted images)
                break
            pairs.append(f"{query} {names[r]}\n")
            kapture.append(f"{query}, {names[r]}, {score:.6g}\n")
    for out, lines in ((pairs_out, pairs), (kapture_out, kapture)):
        with atomic_path(out) as tmp:
            tmp.write_text("".join(lines))
