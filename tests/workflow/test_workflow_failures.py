"""The real Snakefile end to end on synthetic datasets when something goes wrong: a killed
run, bad inputs, failing methods and what they withdraw, moved or rotated images."""

from __future__ import annotations

import copy
import logging
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
import zarr
from synthetic import make_dataset
from workflow_helpers import (
    read_rows,
    scheduled_outputs,
    scheduled_stages,
    snakemake,
    snakemake_command,
    table_in_process,
    toy_config,
    write_config,
)

from vprflow.core.paths import PREDICTIONS_CSV, RECALL_CSV, RECALL_TABLE

pytestmark = pytest.mark.workflow
TARGET = "results/recall_toy.csv"


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> tuple[Path, dict]:
    """``(workdir, config)``: a finished run of anyloc_vlad's table on a 4-place toy,
    ``data_root`` relative to the working directory, as Snakemake left it."""
    workdir = tmp_path_factory.mktemp("finished")
    make_dataset(workdir / "data" / "toy", n_places=4)
    config = toy_config("data", methods=["anyloc_vlad"])
    snakemake(workdir, write_config(workdir, config), TARGET)
    return workdir, config


def copy_of(run: tuple[Path, dict], workdir: Path) -> dict:
    """:func:`finished_run` copied into ``workdir`` (modification times kept, so that
    Snakemake finds it finished there too) -> a copy of its config, for the tests that
    start from a good run and then break something."""
    source, config = run
    shutil.copytree(source, workdir, symlinks=True, dirs_exist_ok=True)
    return copy.deepcopy(config)


def test_killed_run_leaves_no_complete_looking_store_and_rerun_finishes(tmp_path):
    make_dataset(tmp_path / "data" / "toy", n_places=40, width=320, height=240)
    # One method: the run to kill is in its features, and the rerun finishes the table.
    config = toy_config(tmp_path / "data", resolution=[320, 240], methods=["anyloc_vlad"])
    path = write_config(tmp_path, config)
    command = snakemake_command(tmp_path, path, TARGET, cores=1)
    process = subprocess.Popen(
        command,
        cwd=tmp_path,
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    features = tmp_path / "results" / "cache" / "features"
    deadline = time.monotonic() + 120
    partial = []
    while time.monotonic() < deadline and process.poll() is None:
        partial = [p for p in features.glob("*.shards/*.zarr.tmp") if (p / "features").exists()]
        if partial:
            break
        time.sleep(0.02)
    os.killpg(process.pid, signal.SIGKILL)
    process.wait()
    assert partial, "the features stage was never caught mid-way"
    # The interrupted shard exists only under its temporary name.
    # `<key>.<writer tag>.zarr.tmp` is built for `<key>.zarr`.
    final = partial[0].with_name(partial[0].name.split(".")[0] + ".zarr")
    assert final.parent.is_dir() and not final.exists()
    assert not (tmp_path / TARGET).exists()
    snakemake(tmp_path, path, "--unlock")
    snakemake(tmp_path, path, TARGET)
    assert len(read_rows(tmp_path / TARGET)) == len(config["datasets"]["toy"]["methods"])
    assert not list((tmp_path / "results" / "cache").glob("**/*.tmp"))


# ------------------------------------------------------------------ bad input


def failing_run(workdir: Path, config: dict) -> str:
    result = snakemake(workdir, write_config(workdir, config), TARGET, check=False)
    assert result.returncode != 0
    assert not (workdir / TARGET).exists()
    assert not list((workdir / "results" / "cache").glob("*/*.zarr")) or all(
        (p / "zarr.json").exists() for p in (workdir / "results" / "cache").glob("*/*.zarr")
    )
    return result.stdout + result.stderr


def test_missing_dataset_folder_names_it(tmp_path):
    text = failing_run(tmp_path, toy_config(tmp_path / "nowhere"))
    assert "folder" in text and str(tmp_path / "nowhere" / "toy") in text


def test_empty_query_folder_names_it(tmp_path):
    make_dataset(tmp_path / "data" / "toy", n_places=4)
    for image in (tmp_path / "data" / "toy" / "query").iterdir():
        image.unlink()
    text = failing_run(tmp_path, toy_config(tmp_path / "data"))
    assert "contains no images" in text and "query" in text


def test_corrupt_image_names_the_file_and_leaves_no_images_or_dataset_store(tmp_path):
    make_dataset(tmp_path / "data" / "toy", n_places=4)
    bad = tmp_path / "data" / "toy" / "ref" / "0002.png"
    bad.write_bytes(b"not a png at all")
    text = failing_run(tmp_path, toy_config(tmp_path / "data"))
    assert str(bad) in text
    assert not list((tmp_path / "results" / "cache").glob("images/*.zarr"))
    assert not list((tmp_path / "results" / "cache").glob("dataset/*.zarr"))


def test_ground_truth_size_mismatch_is_an_error(tmp_path):
    make_dataset(tmp_path / "data" / "toy", n_places=4)
    from synthetic import write_vprbench_ground_truth

    write_vprbench_ground_truth(tmp_path / "data" / "toy" / "ground_truth_new.npy", 3, 4)
    text = failing_run(tmp_path, toy_config(tmp_path / "data"))
    assert "3 ground-truth rows" in text and "4 query images" in text


def test_unknown_config_key_is_named(tmp_path):
    config = toy_config(tmp_path / "data")
    config["segvlad"]["ordr"] = 2
    text = failing_run(tmp_path, config)
    assert "ordr" in text and "segvlad" in text


def test_missing_17places_images_say_where_to_put_them(tmp_path):
    config = toy_config(tmp_path / "data")
    from workflow_helpers import repo_config

    config["datasets"] = repo_config()["datasets"]
    config["targets"] = []
    result = snakemake(
        tmp_path, write_config(tmp_path, config), "results/recall_17places.csv", "-n", check=False
    )
    text = result.stdout + result.stderr
    assert result.returncode != 0
    assert str(tmp_path / "data" / "17places") in text and "VPR-Bench" in text
    # A preset: its published layout too.
    assert "ground_truth_new.npy" in text and "preset" in text


@pytest.mark.parametrize(
    "target",
    [
        "results/pairs/toyy/anyloc_vlad/pairs.txt",
        "results/export/toyy/anyloc_vlad.npz",
        "results/figures/toyy/retrievals/anyloc_vlad.png",
    ],
)
def test_a_target_naming_an_unknown_dataset_names_it_and_the_configured_ones(tmp_path, target):
    make_dataset(tmp_path / "data" / "toy", n_places=4)
    config_path = write_config(tmp_path, toy_config(tmp_path / "data"))
    result = snakemake(tmp_path, config_path, "-n", target, check=False)
    text = result.stdout + result.stderr
    assert result.returncode != 0
    assert "unknown dataset 'toyy'; configured: ['toy']" in text
    assert "its methods" not in text


def test_unused_dataset_is_not_touched(tmp_path):
    make_dataset(tmp_path / "data" / "toy", n_places=4)
    config = toy_config(tmp_path / "data")
    config["datasets"]["absent"] = copy.deepcopy(config["datasets"]["toy"]) | {"path": "absent"}
    snakemake(tmp_path, write_config(tmp_path, config), "-n", TARGET)
    shutil.rmtree(tmp_path / "data")


def test_a_failing_method_withdraws_the_previous_table(tmp_path, finished_run):
    """A good run, then a method that fails: the old table must not stay looking current."""
    config = copy_of(finished_run, tmp_path)
    assert (tmp_path / TARGET).exists()
    assert scheduled_outputs(tmp_path, write_config(tmp_path, config), TARGET) == []
    # 10,000 clusters from 8 images' patches: the vocabulary stage fails.
    config["methods"]["broken"] = {"aggregator": "anyloc_vlad", "vocabulary": {"n_clusters": 10000}}
    config["datasets"]["toy"]["methods"] = ["anyloc_vlad", "broken"]
    result = snakemake(tmp_path, write_config(tmp_path, config), TARGET, check=False)
    assert result.returncode != 0
    assert "vocabulary.n_clusters = 10000" in result.stdout + result.stderr
    assert not (tmp_path / TARGET).exists()
    assert not (tmp_path / "results" / "predictions_toy.csv").exists()
    assert (tmp_path / (TARGET + ".stale")).exists()


def test_moved_data_reruns_nothing_and_a_replaced_image_reruns_everything(tmp_path, finished_run):
    """The images key covers the images' contents, not their location."""
    config = copy_of(finished_run, tmp_path)  # data_root relative to the working directory
    relative = write_config(tmp_path, config, "relative.yaml")
    snakemake(tmp_path, relative, TARGET)
    absolute = write_config(tmp_path, config | {"data_root": str(tmp_path / "data")}, "abs.yaml")
    assert scheduled_stages(tmp_path, absolute, TARGET) == set()
    snakemake(tmp_path, absolute, TARGET)  # a real run through the other path: nothing to do
    assert scheduled_stages(tmp_path, relative, TARGET) == set()
    (tmp_path / "data").rename(tmp_path / "moved")
    moved = write_config(tmp_path, config | {"data_root": "moved"}, "moved.yaml")
    assert scheduled_stages(tmp_path, moved, TARGET) == set()
    # A different image with an older modification time (as `cp -p` or `tar` leave it).
    ref = sorted((tmp_path / "moved" / "toy" / "ref").iterdir())
    before = ref[0].stat()
    shutil.copyfile(ref[1], ref[0])
    os.utime(ref[0], ns=(before.st_atime_ns, before.st_mtime_ns - 10**9))
    assert scheduled_stages(tmp_path, moved, TARGET) == {
        "images",
        "dataset",
        "features",
        "vocabulary",
        "descriptors",
        "recall",
        "recall_csv",
    }


def test_pca_beyond_the_sample_rank_is_capped_and_reported(tmp_path, caplog):
    """1024 components from a few dozen segment descriptors used to whiten zero-variance
    axes by 1/sqrt(1e-300): inf in the PCA store, NaN descriptors, a believable table.
    The stages run in this process: what caps is the PCA stage."""
    make_dataset(tmp_path / "data" / "toy", n_places=4)
    config = toy_config(tmp_path / "data")
    config["pca"]["dim"] = 1024
    config["datasets"]["toy"]["methods"] = ["segvlad"]
    caplog.set_level(logging.INFO, logger="vprflow")
    (row,) = read_rows(table_in_process(config, tmp_path, "toy"))
    pca = zarr.open_group(str(next((tmp_path / "results/cache/pca").glob("*.zarr"))), mode="r")
    n_samples = int(pca.attrs["n_samples"])
    assert row["pca.dim"] == "1024" and pca.attrs["requested_dim"] == 1024
    assert int(row["descriptor_dim"]) == int(pca.attrs["dim"]) < n_samples < 1024
    assert np.isfinite(np.asarray(pca["explained_variance"][...])).all()
    assert "capped" in caplog.text


# ------------------------------------------------------------------ inputs you can trust


def recall_columns(path: Path) -> list[dict]:
    return [
        {k: v for k, v in row.items() if k.startswith(("method", "recall@", "map@"))}
        for row in read_rows(path)
    ]


def test_queries_stored_rotated_with_an_exif_tag_give_the_upright_table(tmp_path):
    """Phone photos: pixels stored turned, with an Orientation tag (as cv2.imread reads).
    The stages run in this process: what turns them is the images stage's reader."""
    from PIL import Image

    tables = []
    for name, tagged in (("upright", False), ("tagged", True)):
        root = tmp_path / name
        toy = make_dataset(root / "data" / "toy", n_places=5)
        for path in sorted((toy / "query").iterdir()):
            pixels = np.asarray(Image.open(path))
            path.unlink()
            exif = Image.Exif()
            if tagged:
                exif[0x0112] = 6  # stored turned: "rotate 90 degrees clockwise to view"
                pixels = np.ascontiguousarray(np.rot90(pixels, k=1))
            Image.fromarray(pixels).save(path.with_suffix(".png"), exif=exif.tobytes())
        config = toy_config(root / "data")
        config["datasets"]["toy"]["methods"] = ["anyloc_vlad", "segvlad_o0_nopca"]
        tables.append(recall_columns(table_in_process(config, root, "toy")))
    assert tables[0] == tables[1]


def test_a_config_that_cannot_be_planned_withdraws_no_table(tmp_path, finished_run):
    """A trained model whose checkpoint is not fetched yet (the first run of
    config/trained.yaml, as documented) or a local model that is missing stops the plan
    before any job ran: the tables built before still describe the stores they were
    built from, so none is withdrawn (they were renamed to *.stale), a dry run or not,
    and the config that built them has nothing to do."""
    config = copy_of(finished_run, tmp_path)
    good = write_config(tmp_path, config, "good.yaml")
    snakemake(tmp_path, good, TARGET)
    tables = [tmp_path / t.format(dataset="toy") for t in (RECALL_CSV, PREDICTIONS_CSV)]
    built = [(t.read_bytes(), t.stat().st_mtime_ns) for t in tables]
    trained = copy.deepcopy(config)
    trained["backbones"]["nv"] = {"backbone": "netvlad", "checkpoint": str(tmp_path / "nv.ckpt")}
    trained["methods"]["nv"] = {"aggregator": "model", "features": "nv"}
    trained["datasets"]["toy"]["methods"] = ["anyloc_vlad", "nv"]
    local = copy.deepcopy(config)
    local["backbones"]["mine"] = {"backbone": "dinov2", "model": str(tmp_path / "no-model")}
    local["methods"]["mine"] = {"aggregator": "anyloc_vlad", "features": "mine"}
    local["datasets"]["toy"]["methods"] = ["anyloc_vlad", "mine"]
    named = {"trained.yaml": ("nv.ckpt", "trained_checkpoints"), "local.yaml": ("no-model",)}
    for name, broken in (("trained.yaml", trained), ("local.yaml", local)):
        path = write_config(tmp_path, broken, name)
        for args in (("-n", TARGET), (TARGET,)):
            result = snakemake(tmp_path, path, *args, check=False)
            output = result.stdout + result.stderr
            assert result.returncode != 0, output[-3000:]
            assert all(text in output for text in named[name]), output[-3000:]
            assert "withdrawn" not in output and not list(tmp_path.glob("results/**/*.stale"))
            assert [(t.read_bytes(), t.stat().st_mtime_ns) for t in tables] == built
    assert scheduled_outputs(tmp_path, good, TARGET) == []


def test_a_failure_withdraws_only_the_tables_of_the_datasets_it_asked_for(tmp_path, finished_run):
    """toy and mine are finished; runs for mine alone then fail (a mistyped target or a
    method that cannot be planned: no table is withdrawn; a ground-truth file that cannot
    be read, with toy's folder gone from data_root: mine's only): toy's tables stay, and
    a good run names only mine's."""
    config = copy_of(finished_run, tmp_path)
    make_dataset(tmp_path / "data" / "mine", n_places=4, seed=1)
    config["datasets"]["mine"] = copy.deepcopy(config["datasets"]["toy"]) | {"path": "mine"}
    config["targets"] = ["toy", "mine"]
    path = write_config(tmp_path, config)
    toy = [t.format(dataset="toy") for t in (RECALL_CSV, PREDICTIONS_CSV, RECALL_TABLE)]
    mine = RECALL_CSV.format(dataset="mine")
    snakemake(tmp_path, path, *toy, mine)  # the tables (figures would add nothing here)

    def toy_tables_stand():
        return all((tmp_path / t).exists() for t in toy) and not list(
            tmp_path.glob("results/**/*.stale")
        )

    typo = snakemake(tmp_path, path, "--config", "targets=[mien]", check=False)
    assert typo.returncode != 0 and "names datasets ['mien']" in typo.stderr
    assert toy_tables_stand() and (tmp_path / mine).exists()
    broken = copy.deepcopy(config)
    broken["backbones"]["gone"] = {"backbone": "dinov2", "model": str(tmp_path / "no-model")}
    broken["methods"]["gone"] = {"aggregator": "anyloc_vlad", "features": "gone"}
    broken["datasets"]["mine"]["methods"] = ["anyloc_vlad", "gone"]
    result = snakemake(tmp_path, write_config(tmp_path, broken, "broken.yaml"), mine, check=False)
    assert result.returncode != 0 and "backbones.gone.model" in result.stderr
    assert toy_tables_stand() and (tmp_path / mine).exists()
    # toy cannot be listed (the plan cannot tell its tables stale), and mine's ground
    # truth cannot be read: the run asked for mine fails in mine's dataset job.
    (tmp_path / "data" / "toy").rename(tmp_path / "toy-elsewhere")
    (tmp_path / "data" / "mine" / "ground_truth_new.npy").write_bytes(b"not an array")
    result = snakemake(tmp_path, path, mine, check=False)
    assert result.returncode != 0
    assert all((tmp_path / t).exists() for t in toy), result.stdout
    assert (tmp_path / (mine + ".stale")).exists() and not (tmp_path / mine).exists()
    make_dataset(tmp_path / "data" / "mine", n_places=4, seed=1)
    result = snakemake(tmp_path, path, mine)
    closing = [line for line in result.stdout.splitlines() if line.startswith("vprflow: ")]
    assert any(line.startswith("vprflow: mine: ") for line in closing), closing
    assert not any("toy" in line for line in closing), closing


def test_a_report_without_the_runs_data_root_fails_naming_it(tmp_path, finished_run):
    """A report that cannot list the dataset finds none of the run's stores: it used to
    exit 0 with a few of its items and "Missing metadata" warnings."""
    path = write_config(tmp_path, copy_of(finished_run, tmp_path))
    snakemake(tmp_path, path)  # the default target: the figures too
    (tmp_path / "data").rename(tmp_path / "moved")
    result = snakemake(tmp_path, path, "--report", "report.html", check=False)
    assert result.returncode != 0 and not (tmp_path / "report.html").exists()
    assert (
        "dataset 'toy': its images cannot be read under data_root 'data' (dataset 'toy': "
        "folder data/toy does not exist)" in result.stderr
    )
    assert "--config data_root=" in result.stderr
    moved = ("--config", "data_root=moved")
    snakemake(tmp_path, path, "--report", "report.html", *moved)
    assert "recall_toy.csv" in (tmp_path / "report.html").read_text()


def test_a_dataset_that_cannot_be_listed_withdraws_its_tables(tmp_path, finished_run):
    config = copy_of(finished_run, tmp_path)
    assert scheduled_outputs(tmp_path, write_config(tmp_path, config), TARGET) == []
    # An image in a format that is not read: never skipped (it would shift the queries).
    gif = tmp_path / "data/toy/query/0001b.gif"
    gif.write_bytes(b"GIF89a\x01\x00\x01\x00\x00\x00\x00;")
    result = snakemake(tmp_path, write_config(tmp_path, config), TARGET, check=False)
    assert result.returncode != 0
    assert "0001b.gif is a GIF image" in result.stdout + result.stderr
    assert not (tmp_path / TARGET).exists()
    assert (tmp_path / (TARGET + ".stale")).exists()
