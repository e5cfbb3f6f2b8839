"""Without the `slurm` extra the SLURM profile stops in Snakemake's argument parser, before
any vprflow code runs: the documents that give the profile say to install the extra and
quote the line Snakemake ends with, which this checks against Snakemake itself."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

from workflow_helpers import SNAKEFILE

REPO = Path(__file__).resolve().parents[2]
EXTRA = 'pip install -e ".[slurm]"'
PROFILE = REPO / "workflow" / "profiles" / "slurm"
# Every place that gives the SLURM profile's command.
DOCUMENTS = (REPO / "README.md", REPO / "docs" / "cluster.md", PROFILE / "config.yaml")
# Imported at Python's start (PYTHONPATH): Snakemake then finds no SLURM executor plugin,
# as on an install without the extra.
HIDE_PLUGIN = """
import importlib.abc, pkgutil, sys
_iter = pkgutil.iter_modules
pkgutil.iter_modules = lambda path=None, prefix="": (
    m for m in _iter(path, prefix) if "snakemake_executor_plugin_slurm" not in m.name
)
class _Hide(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.startswith("snakemake_executor_plugin_slurm"):
            raise ModuleNotFoundError(name)
sys.meta_path.insert(0, _Hide())
"""


def test_without_the_extra_the_profile_ends_with_the_line_the_documents_quote(tmp_path):
    shim = tmp_path / "shim"
    shim.mkdir()
    (shim / "sitecustomize.py").write_text(HIDE_PLUGIN)
    command = [sys.executable, "-m", "snakemake", "--snakefile", str(SNAKEFILE)]
    command += ["--directory", str(tmp_path), "--profile", str(PROFILE), "-n"]
    result = subprocess.run(
        command,
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(shim)},
    )
    assert result.returncode == 2
    last = result.stderr.strip().splitlines()[-1]
    quoted = re.sub(r"^\S+: error: ", "", last)  # the program's name: snakemake, __main__.py
    assert quoted.startswith("argument --executor/-e: invalid choice: 'slurm'"), last
    for document in DOCUMENTS[1:]:
        assert quoted in document.read_text(), document
    assert not (tmp_path / ".snakemake").exists() and not (tmp_path / "results").exists()


def test_every_document_giving_the_slurm_profile_says_to_install_the_extra_first():
    for document in DOCUMENTS:
        text = document.read_text()
        first = text.index("--profile workflow/profiles/slurm")
        assert EXTRA in text[:first], f"{document.relative_to(REPO)}: the profile before {EXTRA}"
