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
from vprflow.stages.dataset import Dataset


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


def write_pairs(dataset_path: str, recall_path: str, pairs_out: str, kapture_out: str) -> None:
    """Each query's ranked references, in the order the recall stage scored them (its
    ``ranking [Nq, K]``, K the deepest Recall@N; a short ranking ends early), as:

    - ``pairs_out``: ``query reference`` per line (hloc's retrieval pairs,
      ``pairs_from_retrieval``), best first;
    - ``kapture_out``: kapture's pairs file, ``query, reference, score`` per line, the
      score as stored (a comment line says which kind).

    Names are image paths relative to the dataset folder (hloc's and kapture's image
    names when their image root is that folder)."""
    dataset = Dataset(dataset_path)
    result = stores.open_store(recall_path)
    ranking = np.asarray(result["ranking"][...])
    scores = np.asarray(result["scores"][...])
    kind = result.attrs["score"]
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
