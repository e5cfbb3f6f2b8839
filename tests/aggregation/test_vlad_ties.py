"""VLAD's hard assignment breaks float32 ties as the authors' code does, on every BLAS
code path this machine can force.

The authors' operations are written as direct torch formulas in
``tests/tie_problems.py`` (AnyLoc: fast_pytorch_kmeans' cosine ``predict``; SegVLAD:
``func_vpr.vlad_single``), on patches in their layout. Each code path runs in its own
process, because OpenBLAS, MKL and ATen pick their kernels once, at load: numpy's
OpenBLAS (``OPENBLAS_CORETYPE``: the core types this CPU can run, others crash), torch's
ATen kernels (``ATEN_CPU_CAPABILITY``) and torch's MKL matmul (``MKL_CBWR``,
``MKL_ENABLE_INSTRUCTIONS``). The problems hold hundreds of exact and one-to-four-ulp
ties, where a numpy product assigns 80-150 of 600 patches otherwise.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from code_paths import code_paths, path_environment

SCRIPT = Path(__file__).parents[1] / "tie_problems.py"


PATHS = code_paths()
SEEDS = (0, 1)


@pytest.fixture(scope="module")
def results() -> dict[str, list[dict]]:
    """Every code path's counts, the processes started together (each loads torch)."""
    running = {
        name: subprocess.Popen(
            [sys.executable, str(SCRIPT), *map(str, SEEDS)],
            env=path_environment(env),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for name, env in PATHS.items()
    }
    out = {}
    for name, process in running.items():
        stdout, stderr = process.communicate(timeout=300)
        assert process.returncode == 0, f"{name}: {stderr[-2000:]}"
        out[name] = json.loads(stdout)
    return out


@pytest.mark.parametrize("path", sorted(PATHS))
def test_vlad_labels_equal_the_authors_torch_operation_under(path, results):
    for counts in results[path]:
        assert counts["anyloc_mismatches"] == 0, counts
        assert counts["segvlad_mismatches"] == 0, counts
        assert counts["anyloc_vlad_equal"] and counts["segvlad_vlad_equal"], counts


def test_tie_problems_hold_ties_that_a_numpy_product_breaks_otherwise(results):
    """The check can fail: the problems are full of ties, and numpy's own product (the
    vocabulary's assignment) sends many of them elsewhere."""
    for counts in results["default"]:
        assert counts["exact_ties"] > 50 and counts["near_ties"] > 50, counts
        assert counts["numpy_vs_anyloc"] > 0, counts
