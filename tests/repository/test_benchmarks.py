"""Every benchmark still runs: ``benchmarks/bench_*.py --smoke`` (tiny sizes, one repeat,
CPU only, no network, random-weight models) exits with status 0 and prints its table.

The scripts are found by name, so a new benchmark is covered without listing it here;
benchmarks/README.md states what each must do for it. Nothing else runs them, and a
benchmark that nobody runs breaks unseen when the code under it changes.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from workflow_helpers import in_ci

REPO = Path(__file__).resolve().parents[2]
BENCHMARKS = sorted((REPO / "benchmarks").glob("bench_*.py"))
# A benchmark that cannot run here (bench_workflow.py without $VPRFLOW_DATA) says so
# with the status test harnesses read as "skipped" (automake, meson).
SKIPPED = 77
# A table's rule under its header: dashes, or a Markdown |---|---| line.
RULE = re.compile(r"^\s*\|?\s*-{3,}[-|: ]*$")

pytestmark = pytest.mark.benchmark


def printed_a_table(stdout: str) -> bool:
    """A rule line followed by at least one row."""
    lines = stdout.splitlines()
    return any(
        RULE.match(line) and i + 1 < len(lines) and lines[i + 1].strip()
        for i, line in enumerate(lines)
    )


def test_the_benchmarks_are_found():
    # An empty glob (a moved folder) would otherwise leave nothing to fail.
    assert BENCHMARKS, f"no bench_*.py in {REPO / 'benchmarks'}"


@pytest.mark.parametrize("script", BENCHMARKS, ids=lambda path: path.stem)
def test_benchmark_runs_in_smoke_mode(script: Path, request):
    env = dict(os.environ)
    if "from smoke_run import" in script.read_text():  # it reads the run they share
        env["VPRFLOW_SMOKE_RUN"] = str(request.getfixturevalue("benchmarks_smoke_run"))
    start = time.perf_counter()
    result = subprocess.run(
        [sys.executable, str(script), "--smoke"],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
    )
    seconds = time.perf_counter() - start
    output = f"--- stdout\n{result.stdout}\n--- stderr\n{result.stderr[-4000:]}"
    if result.returncode == SKIPPED:
        message = f"{script.name} --smoke: {result.stdout.strip()}"
        if in_ci():
            pytest.fail(message, pytrace=False)
        pytest.skip(message)
    assert result.returncode == 0, f"{script.name} --smoke failed after {seconds:.0f} s\n{output}"
    assert printed_a_table(result.stdout), f"{script.name} --smoke printed no table\n{output}"


def test_a_table_is_a_rule_and_a_row():
    assert printed_a_table("a  b\n----\n1  2\n")
    assert printed_a_table("a | b\n---|---\n1 | 2\n")
    assert printed_a_table("| a | b |\n|---|---|\n| 1 | 2 |\n")
    assert not printed_a_table("a  b\n----\n")
    assert not printed_a_table("done in 3 s\n")
