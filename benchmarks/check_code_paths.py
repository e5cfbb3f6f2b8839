"""The shipped datasets' stores and tables under every code path this CPU can force
(tests/code_paths.py: OpenBLAS core types, the environment's setting unset, ATen
capabilities, MKL's conditional reproducibility and instruction sets, one and two threads,
numpy's loops without AVX-512), each path's run beside the environment's own.

    python benchmarks/check_code_paths.py --data ../shared/data [--datasets corridor,roadscene]
        [--paths openblas_unset,mkl_cbwr_compatible] [--stages features,vocabulary]

Each path runs the dataset's stages of the shipped config in a child process of its own
(``tests/code_paths.py``, every stage in one process, unsharded, on the CPU). Rows: per
dataset and path, the stages whose stores differ from the ``default`` path's (count of
stores), the largest difference of a float array there, and whether every table value
(recall, mAP, precision-recall, counts) is equal. ``tests/workflow/test_code_paths.py`` asserts
what must hold; this prints where the rest moves (docs/methods.md §3, "One table on every
machine").
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
sys.path.insert(0, str(REPO / "src"))

from code_paths import child_result, code_paths, start_child  # noqa: E402


def largest_difference(a: Path, b: Path) -> float:
    from vprflow.core.stores import array_items, open_store

    largest = 0.0
    other = dict(array_items(open_store(b)))
    for name, array in array_items(open_store(a)):
        x, y = array[...], other[name][...]
        if x.dtype.kind == "f" and x.shape == y.shape and x.size:
            largest = max(largest, float(np.nanmax(np.abs(x.astype(float) - y.astype(float)))))
    return largest


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="the shared datasets")
    parser.add_argument("--datasets", default="corridor,roadscene")
    parser.add_argument("--paths", help="comma-separated code paths (default: all)")
    parser.add_argument("--stages", help="comma-separated stages run (default: all)")
    args = parser.parse_args()
    paths = code_paths()
    chosen = ["default"] + [p for p in (args.paths or ",".join(paths)).split(",") if p != "default"]
    print("| dataset | path | seconds | stores differ (by stage) | largest diff | tables equal |")
    print("|---|---|---:|---|---:|---|")
    failed = False
    with tempfile.TemporaryDirectory() as scratch:
        for dataset in args.datasets.split(","):
            runs = {}
            for path in chosen:
                out = Path(scratch) / path  # the child writes under out/<dataset>
                start = time.perf_counter()
                stages = args.stages.split(",") if args.stages else None
                child = start_child(args.data, out, {dataset: stages}, paths[path])
                runs[path] = child_result(child, f"{dataset} under {path}")[dataset]
                seconds = time.perf_counter() - start
                base, run = runs["default"], runs[path]
                differ = [k for k, v in run["stores"].items() if base["stores"].get(k) != v]
                stages = Counter(k.split()[0] for k in differ)
                largest = max(
                    (
                        largest_difference(
                            Path(scratch)
                            / "default"
                            / dataset
                            / k.split()[0]
                            / f"{k.split()[1]}.zarr",
                            out / dataset / k.split()[0] / f"{k.split()[1]}.zarr",
                        )
                        for k in differ
                    ),
                    default=0.0,
                )
                equal = run["tables"] == base["tables"]
                failed |= not equal
                by_stage = ", ".join(f"{s} {n}" for s, n in stages.items()) or "none"
                print(
                    f"| {dataset} | {path} | {seconds:.0f} | {by_stage} | {largest:.1e} | "
                    f"{'yes' if equal else 'NO'} |",
                    flush=True,
                )
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
