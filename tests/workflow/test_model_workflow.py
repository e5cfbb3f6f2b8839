"""The whole DAG with tiny random DINOv2 / DINO / SAM checkpoints loaded through the
real loaders, and with the authors' published HDF5 / c_centers.pt artefacts imported."""

from __future__ import annotations

import csv
import re

import h5py
import numpy as np
import pytest
import torch
from synthetic import make_dataset
from tiny_models import save_tiny_dino, save_tiny_dinov2, save_tiny_sam
from workflow_helpers import expected_rows, repo_config, snakemake, toy_config, write_config

from vprflow.data.images import scan_images

pytestmark = pytest.mark.workflow


def rows_of(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def test_every_model_stage_through_the_dag_with_tiny_dinov2_and_tiny_sam(tmp_path):
    """The shipped config's model backbones and segmenter, made tiny, on a toy dataset in
    corridor's layout under its name (its entry's settings: resolution, truth, PCA): what
    a run proves does not need corridor's 222 photos (16 CPU s of the 45)."""
    make_dataset(tmp_path / "data" / "corridor")
    config = repo_config()
    config["data_root"] = str(tmp_path / "data")
    config["backbones"]["dinov2_vitg14"].update(
        model=str(save_tiny_dinov2(tmp_path / "dinov2")), layer=1
    )
    config["segmenters"]["sam_vith"].update(
        model=str(save_tiny_sam(tmp_path / "sam")),
        points_per_side=6,
        pred_iou_thresh=0.0,
        stability_score_thresh=0.0,
        batch_size=3,  # images per encoder pass through the rule (ragged last batch)
    )
    config["datasets"]["corridor"]["defaults"] = {
        "features": "dinov2_vitg14",
        "segmenter": "sam_vith",
        "pca": {"dim": 32},
    }
    # A global and a per-segment method (every model stage: features, segments, the
    # vocabulary on model features) and one re-ranked row, on the same (model) features.
    config["datasets"]["corridor"]["methods"] = ["anyloc_vlad", "segvlad"]
    config["rerankers"]["mnn"]["features"] = "dinov2_vitg14"
    config["datasets"]["corridor"]["rerank"] = {"anyloc_vlad": ["mnn"]}
    config["vocabulary"]["n_clusters"] = 8
    path = write_config(tmp_path, config)
    dry = snakemake(tmp_path, path, "-n", "results/recall_corridor.csv").stdout
    # Model stages ask the scheduler for a GPU (device auto), the others do not: the
    # matching of model features does, and so does the k-means on them; scoring the
    # stored pairs does not.
    jobs = re.findall(r"rule (\w+):.*?resources: ([^\n]*)", dry, flags=re.DOTALL)
    gpu = {rule: "gpu=1" in resources for rule, resources in jobs}
    assert gpu["features"] and gpu["segments"] and gpu["matches"] and gpu["vocabulary"]
    assert not gpu["rerank"]
    snakemake(tmp_path, path, "results/recall_corridor.csv")
    rows = rows_of(tmp_path / "results" / "recall_corridor.csv")
    assert [r["method"] for r in rows] == expected_rows(config["datasets"]["corridor"])
    for row in rows:
        assert row["features.backbone"] == "dinov2" and row["features.layer"] == "1"
        assert 0.0 <= float(row["recall@1"]) <= float(row["recall@20"]) <= 1.0
    segvlad = next(r for r in rows if r["method"] == "segvlad")
    assert segvlad["segmenter.segmenter"] == "sam" and segvlad["pca.dim"] == "32"


def test_snsm_with_tiny_dino_on_a_paired_toy(tmp_path):
    make_dataset(tmp_path / "data" / "toy")
    config = toy_config(tmp_path / "data", methods=["snsm", "gem"])
    config["datasets"]["toy"]["ground_truth"] = {"kind": "pairs"}
    config["datasets"]["toy"]["paired"] = True
    config["datasets"]["toy"]["defaults"] = {"features": "dino_vitb8"}
    config["backbones"]["dino_vitb8"]["model"] = str(save_tiny_dino(tmp_path / "dino"))
    path = write_config(tmp_path, config)
    snakemake(tmp_path, path, "results/recall_toy.csv")
    rows = rows_of(tmp_path / "results" / "recall_toy.csv")
    assert [r["method"] for r in rows] == ["snsm", "gem"]
    assert rows[0]["features.backbone"] == "dino" and rows[0]["ground_truth"] == "pairs"
    # 224 x 224 at patch 8: a 28 x 28 grid, so SNSM (u = 4, w = 2) has 56 * 56 values.
    import zarr

    store = next((tmp_path / "results" / "cache" / "descriptors").glob("*.zarr"))
    lengths = {
        zarr.open_group(str(p), mode="r")["descriptors"].shape[1]
        for p in store.parent.glob("*.zarr")
    }
    assert 3136 in lengths


def test_published_artefacts_reproduce_without_any_model(tmp_path):
    """Features, masks and centres imported from files in the authors' layouts."""
    root = make_dataset(tmp_path / "data" / "toy")
    rng = np.random.default_rng(0)
    images = scan_images(root / "ref").paths + scan_images(root / "query").paths
    features_h5, masks_h5 = tmp_path / "dino.h5", tmp_path / "masks.h5"
    with h5py.File(features_h5, "w") as features, h5py.File(masks_h5, "w") as masks:
        for image in images:
            # the published shape [1, D, h, w]
            features[f"{image.name}/ift_dino"] = rng.standard_normal((1, 24, 5, 6)).astype(
                np.float32
            )
            for j in range(7):
                mask = np.zeros((36, 48), dtype=bool)
                mask[rng.integers(0, 30) :][:, rng.integers(0, 40) :][:6, :8] = True
                masks[f"{image.name}/masks/{j}/segmentation"] = mask
    centres = tmp_path / "c_centers.pt"
    torch.save(torch.randn(4, 24), centres)
    config = toy_config(tmp_path / "data", methods=["anyloc_vlad", "segvlad_nopca"])
    config["backbones"]["published_dinov2"]["file"] = str(features_h5)
    config["segmenters"]["published_sam"]["file"] = str(masks_h5)
    config["datasets"]["toy"]["defaults"] = {
        "features": "published_dinov2",
        "segmenter": "published_sam",
        "vocabulary": {"source": "file", "file": str(centres)},
    }
    snakemake(tmp_path, write_config(tmp_path, config), "results/recall_toy.csv")
    rows = rows_of(tmp_path / "results" / "recall_toy.csv")
    assert [r["method"] for r in rows] == ["anyloc_vlad", "segvlad_nopca"]
    assert rows[0]["features.backbone"] == "import" and rows[0]["vocabulary.source"] == "file"
    import zarr

    cache = tmp_path / "results" / "cache"
    (store,) = (cache / "features").glob("*.zarr")
    stored = zarr.open_group(str(store), mode="r")
    expected = np.asarray(h5py.File(features_h5, "r")[f"{images[3].name}/ift_dino"])[0]
    expected = expected.transpose(1, 2, 0) / np.linalg.norm(expected, axis=0)[..., None]
    np.testing.assert_allclose(
        np.asarray(stored["features"][3], dtype=np.float32), expected, atol=2e-3
    )
    (vocabulary,) = (cache / "vocabulary").glob("*.zarr")
    centres_stored = np.asarray(zarr.open_group(str(vocabulary), mode="r")["centres"][...])
    np.testing.assert_array_equal(centres_stored, torch.load(centres, weights_only=True).numpy())
