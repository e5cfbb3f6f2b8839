"""Missing trained-model checkpoints: one plan error names every one (path, config key,
variant, repository, URL, what is known of its SHA-256) and the command that fetches
them; that command's rule keeps a file only when its hash matches, logs each fetch, and
a dry run of it fetches nothing."""

from __future__ import annotations

import copy
import hashlib
from pathlib import Path

import pytest
import yaml
from synthetic import make_dataset
from workflow_helpers import snakemake, toy_config, write_config

from vprflow.core.errors import PlanError
from vprflow.data.download import DownloadError
from vprflow.models import kinds
from vprflow.planning.checkpoints import (
    FETCH_TARGET,
    URL_ENV,
    checkpoint_url,
    fetch_checkpoint,
    fetch_command,
    fetching_checkpoints,
)
from vprflow.planning.config import validate_config
from vprflow.planning.plan import build_plan, deep_merge

REPO = Path(__file__).resolve().parents[2]
SCHEMA = REPO / "workflow" / "schemas" / "config.schema.yaml"


def example_config(data_root: Path) -> dict:
    """config/trained.yaml over config/config.yaml, as Snakemake merges them."""
    base = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    extra = yaml.safe_load((REPO / "config" / "trained.yaml").read_text())
    config = deep_merge(base, extra)
    config["datasets"]["corridor"]["methods"] = extra["datasets"]["corridor"]["methods"]
    config["data_root"] = str(data_root)
    return validate_config(config, SCHEMA)


def test_every_missing_checkpoint_of_the_example_config_is_named_in_one_error(
    tmp_path, monkeypatch
):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv(URL_ENV, raising=False)
    config = example_config(tmp_path)
    (tmp_path / "models").mkdir()
    (tmp_path / "models" / "dino_salad.ckpt").write_bytes(b"present")
    with pytest.raises(PlanError) as error:
        build_plan(config, configfiles=["config/config.yaml", "config/trained.yaml"])
    message = str(error.value)
    entries = {
        name: entry
        for name, entry in config["backbones"].items()
        if entry["backbone"] in kinds.TRAINED_KINDS
    }
    absent = {e["checkpoint"] for e in entries.values()} - {"models/dino_salad.ckpt"}
    assert len(absent) == 10 and message.startswith("10 trained-model checkpoint file(s)")
    for name, entry in entries.items():
        if entry["checkpoint"] in absent:
            published = kinds.BACKBONES[entry["backbone"]].spec.variants[entry["variant"]]
            line = next(
                x for x in message.splitlines() if x.startswith(f"  {entry['checkpoint']} ")
            )
            assert f"backbones.{name}.checkpoint" in line and repr(entry["variant"]) in line
            assert published.repository in line and published.url in line
    assert "dino_salad.ckpt" not in message
    assert "SHA-256 begins 0676ba61" in message  # torchvision's, from its file name
    assert message.count("by hand, from the page https://drive.google.com/") == 2
    assert (
        f"snakemake --cores 2 {FETCH_TARGET} --configfile config/config.yaml "
        "config/trained.yaml" in message
    )


def test_an_empty_checkpoint_is_refused_at_planning_naming_it_and_the_fetch(tmp_path, monkeypatch):
    """A 0-byte file (an interrupted copy) was hashed into a key, and the features job
    failed with torch's bare "EOFError"."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv(URL_ENV, raising=False)
    config = example_config(tmp_path)
    for entry in config["backbones"].values():
        if entry["backbone"] in kinds.TRAINED_KINDS:
            Path(entry["checkpoint"]).parent.mkdir(parents=True, exist_ok=True)
            Path(entry["checkpoint"]).write_bytes(b"present")
    Path("models/dino_salad.ckpt").write_bytes(b"")
    with pytest.raises(PlanError) as error:
        build_plan(config, configfiles=["config/config.yaml", "config/trained.yaml"])
    message = str(error.value)
    assert message.startswith("1 trained-model checkpoint file(s) the plan reads are empty:")
    assert "  models/dino_salad.ckpt (empty: 0 bytes, an interrupted download or copy?; " in (
        message
    )
    # Snakemake fetches no file that exists: the empty one goes first.
    assert (
        f"rm models/dino_salad.ckpt && snakemake --cores 2 {FETCH_TARGET} --configfile "
        "config/config.yaml config/trained.yaml" in message
    )
    Path("models/dino_salad.ckpt").unlink()
    with pytest.raises(PlanError, match="are missing:") as error:
        build_plan(config)
    assert "rm " not in str(error.value)


def test_a_plan_built_to_fetch_checkpoints_refuses_every_stage(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    plan = build_plan(example_config(tmp_path), allow_missing_checkpoints=True)
    assert "models/model.safetensors" in plan.checkpoints
    stage, keys = next(iter(plan.stages.items()))
    with pytest.raises(PlanError, match="checkpoint file.* are missing"):
        plan.get(stage, next(iter(keys)))


def test_the_fetch_command_names_each_config_file_once_relative_to_here(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    files = [tmp_path / "config" / "a.yaml", "config/b.yaml", tmp_path / "config" / "a.yaml"]
    assert fetch_command(files) == (
        f"snakemake --cores 2 {FETCH_TARGET} --configfile config/a.yaml config/b.yaml"
    )
    assert fetching_checkpoints((FETCH_TARGET,))
    assert not fetching_checkpoints(("results/recall_x.csv",))


def test_a_mirror_serves_every_file_and_a_page_is_no_download_url(monkeypatch):
    mixvpr = kinds.BACKBONES["mixvpr"].spec.variants["resnet50_4096"]
    salad = kinds.BACKBONES["salad"].spec.variants["dino_salad"]
    monkeypatch.delenv(URL_ENV, raising=False)
    assert checkpoint_url(mixvpr) is None and checkpoint_url(salad) == salad.url
    monkeypatch.setenv(URL_ENV, "file:///mirror/")
    assert checkpoint_url(mixvpr) == f"file:///mirror/{mixvpr.file}"


def test_a_fetch_keeps_the_file_only_when_its_hash_matches(tmp_path):
    source = tmp_path / "mirror" / "w.pth"
    source.parent.mkdir()
    source.write_bytes(b"weights")
    sha256 = hashlib.sha256(b"weights").hexdigest()
    out = tmp_path / "models" / "w.pth"
    with pytest.raises(DownloadError, match=f"expected sha256 {'0' * 64}, got {sha256}"):
        fetch_checkpoint(source.as_uri(), "0" * 64, out)
    assert not list(out.parent.iterdir())  # neither the file nor a temporary
    with pytest.raises(DownloadError, match=r"expected sha256 ffffffff\.\.\."):
        fetch_checkpoint(source.as_uri(), "ffffffff", out)
    assert not list(out.parent.iterdir())
    fetch_checkpoint(source.as_uri(), sha256[:8], out)  # a published prefix
    assert out.read_bytes() == b"weights"


@pytest.mark.workflow
def test_the_fetch_target_fetches_every_missing_checkpoint_and_refuses_a_wrong_one(
    tmp_path, monkeypatch
):
    make_dataset(tmp_path / "data" / "toy", n_places=4, width=64, height=48)
    config = toy_config(tmp_path / "data", resolution=[64, 48], methods=["salad", "trunk"])
    config["backbones"]["salad"] = {"backbone": "salad", "checkpoint": "models/dino_salad.ckpt"}
    config["backbones"]["trunk"] = {
        "backbone": "resnet50",
        "checkpoint": str(tmp_path / "elsewhere" / "resnet50-0676ba61.pth"),
    }
    config["methods"] = {
        "salad": {"aggregator": "model", "features": "salad"},
        "trunk": {"aggregator": "anyloc_vlad", "features": "trunk"},
    }
    path = write_config(tmp_path, config)
    mirror = tmp_path / "mirror"
    mirror.mkdir()
    (mirror / "dino_salad.ckpt").write_bytes(b"salad weights")
    (mirror / "resnet50-0676ba61.pth").write_bytes(b"not torchvision's")
    monkeypatch.setenv(URL_ENV, mirror.as_uri())

    planned = snakemake(tmp_path, path, "-n", check=False)
    assert planned.returncode != 0
    said = planned.stdout + planned.stderr
    assert "2 trained-model checkpoint file(s)" in said, said[-3000:]
    assert f"snakemake --cores 2 {FETCH_TARGET} --configfile" in said

    dry = snakemake(tmp_path, path, FETCH_TARGET, "-n")
    assert dry.stdout.count("vprflow: fetching") == 2
    assert not (tmp_path / "models").exists() and not (tmp_path / "logs").exists()

    run = snakemake(tmp_path, path, FETCH_TARGET, "--keep-going", check=False)
    assert run.returncode != 0
    assert (tmp_path / "models" / "dino_salad.ckpt").read_bytes() == b"salad weights"
    log = tmp_path / "logs" / "trained_checkpoint" / "models" / "dino_salad.ckpt.log"
    assert hashlib.sha256(b"salad weights").hexdigest() in log.read_text()
    elsewhere = tmp_path / "elsewhere"  # refused: no file, no temporary
    assert not elsewhere.exists() or not list(elsewhere.iterdir())
    refused = tmp_path / "logs" / "trained_checkpoint" / "absolute" / f"{tmp_path}"[1:]
    refused = refused / "elsewhere" / "resnet50-0676ba61.pth.log"
    assert "expected sha256 0676ba61..." in refused.read_text()

    # With every file in place the plan stands and the target has nothing to do.
    fixed = copy.deepcopy(config)
    fixed["backbones"]["trunk"]["checkpoint"] = "models/trunk.pth"
    (tmp_path / "models" / "trunk.pth").write_bytes(b"put here by hand")
    done = snakemake(tmp_path, write_config(tmp_path, fixed), FETCH_TARGET)
    assert "Nothing to be done" in done.stdout + done.stderr


def test_a_checkpoint_path_naming_a_folder_is_a_plan_error_naming_the_key(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    config = example_config(tmp_path)
    for entry in config["backbones"].values():
        if entry["backbone"] in kinds.TRAINED_KINDS:
            Path(entry["checkpoint"]).parent.mkdir(parents=True, exist_ok=True)
            Path(entry["checkpoint"]).write_bytes(b"present")
    config["backbones"]["netvlad"]["checkpoint"] = "models"  # the folder holding it
    with pytest.raises(PlanError) as error:
        build_plan(config)
    message = str(error.value)
    assert "config key backbones.netvlad.checkpoint: models is a folder; it must name a file" in (
        message
    )
    assert "pitts_WPCA4096.pth.tar" in message  # what the folder holds, to point at it
