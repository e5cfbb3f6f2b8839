"""Side by side: VLAD's hard assignment in vprflow against the authors' own code, on the
same descriptors, under every BLAS code path this machine can force.

Compared per patch (AnyLoc) and per region (SegVLAD):

- AnyLoc: Revisit-Anything's ``utilities.VLAD`` (its ``kmeans.predict``, i.e.
  fast_pytorch_kmeans' cosine ``predict``, and ``generate``) on the patches as its
  ``func_vpr.aggFt`` passes them (``F.normalize(desc [1, D, N], dim=1)``, permuted),
  against vprflow's ``vlad_input`` + ``published_labels(..., "anyloc")`` and ``vlad``;
- SegVLAD: ``func_vpr.vlad_single`` (read from ``func_vpr.py``, its ``'cuda'`` device
  strings replaced by ``'cpu'``: this machine has no GPU; the module itself imports SAM,
  DINO and a GUI toolkit, so only these two functions are compiled) on five regions per
  image (the whole image and its quadrants), against vprflow's ``vlad_per_region``;
- before: vprflow's previous assignment (a numpy product, now the vocabulary's
  ``assign``) against the authors' labels, and the SegVLAD regions it gave.

Descriptors: random problems full of exact and near ties (``tests/tie_problems.py``), and,
with ``--results DIR`` (a finished workflow run's folder), every features store there
with each vocabulary fitted on it: the shipped weight-free corridor and roadscene data.
Each code path runs in a child process with its environment (``OPENBLAS_CORETYPE``,
``ATEN_CPU_CAPABILITY``, ``MKL_CBWR``, ``MKL_ENABLE_INSTRUCTIONS``, one thread). Printed:
per path and input, patches, AnyLoc labels equal / differing, the largest AnyLoc VLAD
difference, SegVLAD regions equal / differing (a region differs when its vector is more
than 1e-4 from the authors'), the numpy labels and regions that differed, the
patches whose two best AnyLoc scores tie exactly or within 4 ulps in the authors'
product, and a digest of the authors' labels (equal digests across code paths: no tie
moved with the CPU). Exits 1 if any label
or region differs.

    git -C /work/.mirror/AnyLoc+Revisit-Anything/repo show HEAD:utilities.py > /tmp/ra/utilities.py
    git -C /work/.mirror/AnyLoc+Revisit-Anything/repo show HEAD:func_vpr.py > /tmp/ra/func_vpr.py
    pip install --target /tmp/deps einops scikit-learn   # then remove its numpy and scipy
    PYTHONPATH=/tmp/deps:/tmp/fpk python benchmarks/check_ties.py /tmp/ra [--results DIR]

``ORIGINALS`` is a Revisit-Anything folder holding ``utilities.py`` and ``func_vpr.py``;
fast_pytorch_kmeans (AnyLoc's k-means, 0.2.2), einops and scikit-learn must be importable.
"""

from __future__ import annotations

import argparse
import ast
import hashlib
import importlib.util
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent

REGION_ATOL = 1e-4


def _authors(originals: Path):
    """``(utilities module, vlad_single)``: their VLAD class, and their SegVLAD function
    compiled from ``func_vpr.py`` with its device strings set to the CPU."""
    import torch
    import torch.nn.functional as F

    spec = importlib.util.spec_from_file_location("utilities", originals / "utilities.py")
    utilities = importlib.util.module_from_spec(spec)
    sys.modules["utilities"] = utilities
    spec.loader.exec_module(utilities)
    path = originals / "func_vpr.py"
    tree = ast.parse(path.read_text(), str(path))
    wanted = {"vlad_single", "vlad_matmuls_per_cluster"}
    body = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name in wanted]
    if {n.name for n in body} != wanted:
        raise SystemExit(f"{path}: expected functions {sorted(wanted)}")
    module = ast.Module(body=body, type_ignores=[])
    for node in ast.walk(module):
        if isinstance(node, ast.Constant) and node.value == "cuda":
            node.value = "cpu"
    namespace = {"torch": torch, "F": F, "time": time, "np": np}
    exec(compile(module, str(path), "exec"), namespace)
    return utilities, namespace["vlad_single"]


def _inputs(results: Path | None):
    """``(name, [raw patch grids [N, D]], centres [K, D])`` for every input."""
    sys.path.insert(0, str(ROOT / "tests"))
    from tie_problems import tie_problem

    for seed in (0, 1, 2):
        raw, centres = tie_problem(seed)
        yield f"tie_problem_{seed}", [raw[:300], raw[300:]], centres
    if results is None:
        return
    from vprflow.core import stores

    cache = results / "results" / "cache"
    features = {p.stem: p for p in sorted((cache / "features").glob("*.zarr"))}
    for path in sorted((cache / "vocabulary").glob("*.zarr")):
        group = stores.open_store(str(path))
        key = dict(group.attrs.get("record", {})).get("inputs", {}).get("features")
        if key not in features:
            continue
        centres = np.asarray(group["centres"][...], np.float32)
        grids = stores.open_store(str(features[key]))["features"]
        images = [np.asarray(grids[i], np.float32) for i in range(grids.shape[0])]
        yield (
            f"features {key} vocabulary {path.stem}",
            [g.reshape(-1, g.shape[-1]) for g in images],
            centres,
        )


def _regions(n: int) -> np.ndarray:
    """The whole image and four interleaved quarters of its patches, bool ``[5, n]``."""
    regions = np.zeros((5, n), dtype=bool)
    regions[0] = True
    for q in range(4):
        regions[1 + q, q::4] = True
    return regions


def child(originals: Path, results: Path | None) -> list[dict]:
    import fast_pytorch_kmeans as fpk
    import torch
    import torch.nn.functional as F

    from vprflow.aggregation.aggregators import vlad_input
    from vprflow.aggregation.vlad import assign, published_labels, vlad, vlad_per_region

    utilities, vlad_single = _authors(originals)
    rows = []
    for name, images, centres in _inputs(results):
        k, d = centres.shape
        authors = utilities.VLAD(k, desc_dim=d)
        authors.kmeans = fpk.KMeans(k, mode="cosine")
        authors.kmeans.centroids = authors.c_centers = torch.from_numpy(centres)
        names = ("patches", "equal", "differ", "seg_equal", "seg_differ", "numpy", "seg_numpy")
        names += ("exact_ties", "near_ties")
        counts = dict.fromkeys(names, 0)
        worst, labels = 0.0, []
        for raw in images:
            desc = torch.from_numpy(np.ascontiguousarray(raw.T))[None]  # their [1, D, N]
            x = F.normalize(desc, dim=1).permute(0, 2, 1).squeeze(0)
            theirs = authors.kmeans.predict(x).numpy()
            labels.append(theirs)
            scores = authors.kmeans.cos_sim(x, authors.kmeans.centroids).numpy()
            top = np.sort(scores, axis=1)[:, -2:]
            gap = (top[:, 1] - top[:, 0]) / np.spacing(np.abs(top[:, 1]))
            counts["exact_ties"] += int((gap == 0).sum())
            counts["near_ties"] += int(((gap > 0) & (gap <= 4)).sum())
            theirs_vlad = authors.generate(x).numpy()
            mine_x = vlad_input(raw, {"normalize_descriptors": True})
            mine = published_labels(mine_x, centres, "anyloc")
            worst = max(worst, float(np.abs(vlad(mine_x, centres) - theirs_vlad).max()))
            regions = _regions(len(raw))
            their_regions = vlad_single(
                x, torch.from_numpy(centres), None, torch.from_numpy(regions)
            )
            their_regions = their_regions[0] if isinstance(their_regions, tuple) else their_regions
            mine_regions = vlad_per_region(mine_x, regions, centres)
            off = np.abs(mine_regions - their_regions.numpy()).max(axis=1) > REGION_ATOL
            counts["patches"] += len(raw)
            counts["equal"] += int((mine == theirs).sum())
            counts["differ"] += int((mine != theirs).sum())
            counts["seg_equal"] += int((~off).sum())
            counts["seg_differ"] += int(off.sum())
            before = assign(np.asarray(x), centres)
            counts["numpy"] += int((before != theirs).sum())
            before_regions = vlad_per_region(mine_x, regions, centres, labels=before)
            off = np.abs(before_regions - their_regions.numpy()).max(axis=1) > REGION_ATOL
            counts["seg_numpy"] += int(off.sum())
        digest = hashlib.sha256(np.concatenate(labels).astype(np.int64).tobytes()).hexdigest()
        rows.append({"input": name, **counts, "vlad_max_diff": worst, "labels": digest[:12]})
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("originals", type=Path, help="Revisit-Anything folder")
    parser.add_argument("--results", type=Path, help="a finished workflow run's folder")
    parser.add_argument("--paths", help="comma-separated code paths (default: all)")
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(child(args.originals, args.results)))
        return 0
    sys.path.insert(0, str(ROOT / "tests"))
    from code_paths import code_paths, path_environment  # as tests/aggregation/test_vlad_ties.py

    paths = code_paths()
    chosen = args.paths.split(",") if args.paths else list(paths)
    print(
        "| code path | input | patches | anyloc equal | anyloc differ | anyloc max vlad diff "
        "| segvlad regions equal | segvlad regions differ | before: numpy labels differ "
        "| before: regions differ | exact ties | near ties | authors' labels |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|")
    failed = False
    for path in chosen:
        command = [sys.executable, __file__, str(args.originals), "--child", path]
        if args.results:
            command += ["--results", str(args.results)]
        done = subprocess.run(
            command, env=path_environment(paths[path]), capture_output=True, text=True
        )
        if done.returncode:
            print(f"| {path} | failed: {done.stderr.strip().splitlines()[-1:]} |")
            failed = True
            continue
        for row in json.loads(done.stdout.strip().splitlines()[-1]):
            failed |= bool(row["differ"] or row["seg_differ"])
            print(
                f"| {path} | {row['input']} | {row['patches']} | {row['equal']} | "
                f"{row['differ']} | {row['vlad_max_diff']:.1e} | {row['seg_equal']} | "
                f"{row['seg_differ']} | {row['numpy']} | {row['seg_numpy']} | "
                f"{row['exact_ties']} | {row['near_ties']} | {row['labels']} |"
            )
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
