"""Random VLAD assignment problems full of exact and near ties, and a child-process entry
point that compares vprflow's assignment with the authors' operation written as a direct
torch formula (tests/aggregation/test_vlad_ties.py runs it under each BLAS code path).

Run as ``python tests/tie_problems.py SEED...``: prints a JSON list, one object of
counts per seed.
"""

from __future__ import annotations

import json
import sys

import numpy as np


def tie_problem(seed: int, n: int = 600, d: int = 384, k: int = 32):
    """``(raw patches [n, d] float32, centres [k, d] float32)``.

    Centres 2 and 3 point the same way (3 = 2 x centre 2, so their unit vectors are
    equal: exact ties), centre 4 = 3 x centre 2 (its unit vector differs in the last
    bits: near ties), centre 1 = centre 0 nudged by 1e-4 along a direction the patches
    near it are orthogonal to (scores equal to ~5e-9: ties or one-ulp near ties, as a
    kernel rounds). A third of the patches lie near centre 0, a third near centre 2, the
    rest anywhere; patches are not unit length (the pipeline normalises them).
    """
    rng = np.random.default_rng(seed)
    centres = rng.standard_normal((k, d)) * rng.uniform(0.3, 1.0, (k, 1))
    u0 = centres[0] / np.linalg.norm(centres[0])
    v = rng.standard_normal(d)
    v -= (v @ u0) * u0
    v /= np.linalg.norm(v)
    centres[1] = np.linalg.norm(centres[0]) * (u0 + 1e-4 * v)
    centres[3] = 2 * centres[2]
    centres[4] = 3 * centres[2]
    u2 = centres[2] / np.linalg.norm(centres[2])
    third = n // 3
    near0 = 3.0 * u0 + rng.standard_normal((third, d)) * 0.05
    near0 -= np.outer(near0 @ v, v)
    near2 = 3.0 * u2 + rng.standard_normal((third, d)) * 0.05
    anywhere = rng.standard_normal((n - 2 * third, d))
    scale = rng.uniform(0.5, 4.0, (n, 1))
    raw = np.concatenate([near0, near2, anywhere]) * scale
    return raw.astype(np.float32), centres.astype(np.float32)


def authors_labels(raw: np.ndarray, centres: np.ndarray):
    """The published operations, written out: ``(AnyLoc labels, SegVLAD labels, AnyLoc
    scores)``. Patches as Revisit-Anything holds them (``F.normalize(desc [1, D, N],
    dim=1).permute(0, 2, 1).squeeze()``); AnyLoc: fast_pytorch_kmeans' cosine
    ``predict`` (``normalize(a) @ normalize(b).T``, ``.max(dim=-1)``); SegVLAD:
    ``func_vpr.vlad_single`` (``argmax(x @ F.normalize(C, dim=1).T, dim=1)``)."""
    import torch
    import torch.nn.functional as F

    desc = torch.from_numpy(np.ascontiguousarray(raw.T))[None]
    x = F.normalize(desc, dim=1).permute(0, 2, 1).squeeze()
    c = torch.from_numpy(centres)
    scores = F.normalize(x, dim=-1) @ F.normalize(c, dim=-1).transpose(-2, -1)
    anyloc = scores.max(dim=-1)[1]
    segvlad = torch.argmax(x @ F.normalize(c, dim=1).T, dim=1)
    return anyloc.numpy(), segvlad.numpy(), scores.numpy()


def compare(seed: int) -> dict:
    """vprflow's assignment (through the aggregators' VLAD input and the VLAD vectors)
    against :func:`authors_labels` on one problem: counts of ties and of mismatches."""
    from vprflow.aggregation.aggregators import vlad_input
    from vprflow.aggregation.vlad import assign, published_labels, vlad, vlad_per_region

    raw, centres = tie_problem(seed)
    anyloc, segvlad, scores = authors_labels(raw, centres)
    x = vlad_input(raw, {"normalize_descriptors": True})
    top = np.sort(scores, axis=1)[:, -2:]
    gap = np.abs(top[:, 1] - top[:, 0]) / np.spacing(top[:, 1])
    # The VLAD vectors must be the ones of the authors' labels: vlad_per_region given
    # those labels is the reference (same arithmetic), so any label moved shows.
    regions = np.ones((1, len(x)), dtype=bool)
    return {
        "patches": len(raw),
        "exact_ties": int((gap == 0).sum()),
        "near_ties": int(((gap > 0) & (gap <= 4)).sum()),
        "anyloc_mismatches": int((published_labels(x, centres, "anyloc") != anyloc).sum()),
        "segvlad_mismatches": int((published_labels(x, centres, "segvlad") != segvlad).sum()),
        "anyloc_vlad_equal": bool(
            np.array_equal(vlad(x, centres), vlad(x, centres, labels=anyloc))
        ),
        "segvlad_vlad_equal": bool(
            np.array_equal(
                vlad_per_region(x, regions, centres),
                vlad_per_region(x, regions, centres, labels=segvlad),
            )
        ),
        "numpy_vs_anyloc": int((assign(x, centres) != anyloc).sum()),
    }


if __name__ == "__main__":
    print(json.dumps([compare(int(seed)) for seed in sys.argv[1:]]))
