"""Shared fixtures: the real datasets under $VPRFLOW_DATA, the SLURM cluster, and a tiny
model of each SAM kind."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from slurm_fixtures import slurm_cluster  # noqa: F401  (re-exported fixture)

# The SLURM executor plugin, where installed (the `slurm` extra), runs `scontrol show
# config` when Snakemake imports it, at every start: 9 s where a slurm.conf names a
# controller that does not answer (or its DNS look-up hangs). Local runs need no cluster,
# so every test not marked `slurm` points SLURM at an empty configuration, which scontrol
# refuses at once; the SLURM tests keep the machine's own.
NO_CLUSTER = {"SLURM_CONF": os.devnull}


@pytest.fixture(autouse=True)
def no_cluster_probe(request, monkeypatch):
    if request.node.get_closest_marker("slurm") is None:
        for name, value in NO_CLUSTER.items():
            monkeypatch.setenv(name, value)


def in_ci() -> bool:
    return os.environ.get("CI", "").lower() in {"1", "true", "yes"}


@pytest.fixture(scope="session")
def data_root() -> Path:
    """``$VPRFLOW_DATA``: missing data skips locally and fails under CI=true."""
    value = os.environ.get("VPRFLOW_DATA")
    if not value or not Path(value).is_dir():
        message = f"VPRFLOW_DATA is {value!r}, not a folder with the shared datasets"
        if in_ci():
            pytest.fail(message, pytrace=False)
        pytest.skip(message)
    return Path(value).resolve()


@pytest.fixture(scope="session")
def corridor_run(tmp_path_factory, data_root):
    """The shipped config's default run (`snakemake` with no target: corridor, tables and
    figures), then `snakemake --report report.html`; shared by the tests that read them.
    Returns ``(workdir, report path)``."""
    from workflow_helpers import repo_config, snakemake, write_config

    workdir = tmp_path_factory.mktemp("corridor")
    config = repo_config()
    config["data_root"] = str(data_root)
    config_path = write_config(workdir, config)
    # A session fixture is set up before the function-scoped no_cluster_probe.
    with pytest.MonkeyPatch.context() as patch:
        for name, value in NO_CLUSTER.items():
            patch.setenv(name, value)
        snakemake(workdir, config_path)
        snakemake(workdir, config_path, "--report", "report.html")
    return workdir, workdir / "report.html"


@pytest.fixture(scope="module", params=("sam", "sam_hq", "sam2"))
def sam_kind_model(request, tmp_path_factory):
    """``(kind, path, model)``: a tiny random model of each SAM kind saved to ``path``
    (``test_sam_adapters``, ``test_sam_generator``). Well-conditioned weights (as
    ``test_sam_generator``'s reference model): float32 logits of separately batched calls
    agree to ~1e-5."""
    from tiny_models import tiny_sam, tiny_sam2, tiny_sam_hq

    kind = request.param
    build = {"sam": tiny_sam, "sam_hq": tiny_sam_hq, "sam2": tiny_sam2}[kind]
    model = build(model_size=128, seed=3, scale=0.3)
    path = tmp_path_factory.mktemp(kind)
    model.save_pretrained(path)
    return kind, path, model
